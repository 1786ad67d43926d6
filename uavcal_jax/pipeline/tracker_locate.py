"""One left-image box -> the target's world point: from the frame's depth image (the box first
redrawn around what the depth shows in it with ``refine.enabled``), else its stereo pair's
disparity, else not at all (with the reason). The localisation of
:class:`~uavcal_jax.pipeline.tracker.TargetTracker`.

A frame's images come as :class:`FrameSensors`, loaded only when a box is located: from a
recording (:func:`recording_sensors`) or from the images a simulator has just rendered.

Frames: ``T_WB`` the body pose (world = the pose's gravity-aligned frame), ``T_BC`` the left
camera's extrinsic from the calibration.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import numpy as np

from uavcal_jax.data.sequence import CameraCalibration, Sequence
from uavcal_jax.geometry.camera import from_calibration
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.track import REASONS, cut_by_border, locate_box
from uavcal_jax.track.depth_box import refine_box
from uavcal_jax.track.locate import box_depth
from uavcal_jax.track.stereo import locate_box_stereo, rectify_stereo

__all__ = ["LOCALISATION_MODES", "FrameSensors", "LocatedPoint", "Localizer", "build_localizer",
           "recording_sensors"]

#: How a recording's boxes are located: from its depth images, its stereo pair, or not at all.
LOCALISATION_MODES = ("depth", "stereo", "off")
#: Why a box was not located, besides the localisation's own :data:`uavcal_jax.track.REASONS`.
NO_POSE, BORDER = "no VIO pose at the frame", "box cut by the image border"


@dataclasses.dataclass(frozen=True)
class FrameSensors:
    """One left frame's images for localisation, each loaded on first call: ``depth()`` the
    left camera's z-depth (H, W) metres, ``stereo()`` the (left, right) uint8 grey pair;
    ``None``: the frame has none (the reason in ``missing``)."""

    depth: Callable[[], np.ndarray] | None = None
    stereo: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
    missing: str = ""


def recording_sensors(sequence: Sequence) -> Callable[[int], FrameSensors]:
    """``frame -> FrameSensors`` of a recording's left frame (its ``depth0`` image and its
    ``cam1`` frame at the same time stamp, where it has them)."""
    left, depth, right = (sequence.camera("cam0"), sequence.depth.get("depth0"),
                          sequence.cameras.get("cam1"))
    depth_at = {} if depth is None else {int(t): i for i, t in enumerate(depth.t_ns)}
    right_at = {} if right is None else {int(t): i for i, t in enumerate(right.t_ns)}

    def at(frame: int) -> FrameSensors:
        t_ns = int(left.t_ns[frame])
        i, j = depth_at.get(t_ns), right_at.get(t_ns)
        # loaded once a frame: its boxes are located one by one (decoding a 752x480 depth
        # PNG takes 6.7 ms on a 2-core Intel Xeon, as long as the box's localisation)
        return FrameSensors(
            None if i is None else functools.cache(lambda: depth.load(i)),
            None if j is None else functools.cache(lambda: (left.load(frame), right.load(j))),
            "no depth image at the frame" if depth is not None else "no right image at the frame")

    return at


@dataclasses.dataclass(frozen=True)
class LocatedPoint:
    """One box's localisation: ``point`` (3,) world metres and ``covariance`` (3, 3) m^2
    (NaN unless ``reason == "located"``); the view it was located in: ``T_WC`` (4, 4) the left
    camera's pose and ``box`` (4,) the box (pixel edges)."""

    point: np.ndarray
    covariance: np.ndarray
    reason: str
    T_WC: np.ndarray = dataclasses.field(default_factory=lambda: np.full((4, 4), np.nan))
    box: np.ndarray = dataclasses.field(default_factory=lambda: np.full(4, np.nan))

    @property
    def located(self) -> bool:
        return self.reason == REASONS[0]


class Localizer:
    """Locates left-image boxes (``mode`` one of :data:`LOCALISATION_MODES`; ``reason`` says
    why it is off) of the left camera ``left`` (and, for ``stereo``, the right camera
    ``right``). For a recording build it with :func:`build_localizer`."""

    def __init__(self, config: RunConfig, mode: str, left: CameraCalibration,
                 right: CameraCalibration | None = None, reason: str = ""):
        self.mode, self.reason = mode, reason
        self._config = config
        self._extent = config.detect.target_extent()
        half = config.detect.target_half_size()
        #: the followed class's horizontal half-diagonal, metres (None: no box model)
        self._radius = None if half is None else float(np.hypot(half[0], half[1]))
        self._size = left.resolution
        self.T_BC = np.asarray(left.T_BS, np.float64)
        #: the left camera's model
        self.camera = from_calibration(left)
        self._locate_cut = (config.detect.locate_cut
                            and config.detect.target_half_size() is not None)
        self._rect = None
        if mode == "stereo":
            self._rect = rectify_stereo(self.camera, from_calibration(right), self.T_BC,
                                        right.T_BS)

    def cut_by_border(self, box) -> bool:
        """The box reaches within ``detect.border_px`` of the image border."""
        return cut_by_border(box, self._size, self._config.detect.border_px)

    def can_locate(self, box) -> bool:
        """A box can be located: inside the image, or cut by its border with
        ``detect.locate_cut`` on and a class with a box model, which is cut there as well
        (:data:`~uavcal_jax.pipeline.run_config.CLASS_HALF_SIZE_M`)."""
        return self._locate_cut or not self.cut_by_border(box)

    def locate(self, box, T_WB: np.ndarray | None, sensors: FrameSensors) -> LocatedPoint:
        """The world point of ``box`` (4,) seen from pose ``T_WB`` (4, 4) (``None``: no pose)
        in a frame with images ``sensors``."""
        nan = LocatedPoint(np.full(3, np.nan), np.full((3, 3), np.nan), self.reason)
        if self.mode == "off":
            return nan
        if T_WB is None or not np.all(np.isfinite(T_WB)):
            return dataclasses.replace(nan, reason=NO_POSE)
        if not self.can_locate(box):
            return dataclasses.replace(nan, reason=BORDER)
        cfg = self._config.locate
        images = sensors.depth if self.mode == "depth" else sensors.stereo
        if images is None:
            return dataclasses.replace(nan, reason=sensors.missing)
        if self.mode == "depth":
            depth = images()
            if self._config.refine.enabled:  # the box redrawn around what the depth sees
                front = float(box_depth(depth, np.asarray(box, np.float32), cfg).depth)
                box = refine_box(box, depth, front, self.camera,
                                 np.asarray(T_WB, np.float64) @ self.T_BC, self._config.refine,
                                 self._radius)
            out = locate_box(np.asarray(box, np.float32), depth, self.camera, self.T_BC,
                             T_WB, self._extent, cfg)
        else:
            out = locate_box_stereo(box, *images(), self._rect, self.T_BC, T_WB, self._extent,
                                    cfg, self._config.stereo)
        return LocatedPoint(np.asarray(out.point, np.float64),
                            np.asarray(out.covariance, np.float64), REASONS[int(out.reason)],
                            np.asarray(T_WB, np.float64) @ self.T_BC, np.asarray(box, np.float64))


def build_localizer(sequence: Sequence, config: RunConfig) -> Localizer:
    """The recording's :class:`Localizer`: ``depth`` with a ``depth0`` stream, else ``stereo``
    with a ``cam1``, else ``off`` with the reason."""
    left = sequence.camera("cam0").calibration
    if "depth0" in sequence.depth:
        return Localizer(config, "depth", left)
    if "cam1" in sequence.cameras:
        try:
            return Localizer(config, "stereo", left, sequence.camera("cam1").calibration)
        except ValueError as err:  # a rig stereo matching cannot use
            return Localizer(config, "off", left, reason=f"localisation off: {err}")
    return Localizer(config, "off", left, reason="localisation off: the recording has no depth "
                     "image (depth0) and no right camera (cam1)")
