"""Detections -> the target to follow, located and filtered in the VIO's world frame.

The middle of ``uavcal run`` (:func:`uavcal_jax.pipeline.run.run_pipeline`), after the VIO
and the detector have run over a recording:

1. the detections of every detected frame, less the boxes of a part of a larger one
   (:func:`uavcal_jax.track.associate.contained_duplicates`), are associated into tracks
   (:func:`uavcal_jax.track.associate.assign_track_ids`), two boxes of the class followed
   taken for one target only where they are located where it could have driven between them
   (:func:`_same_target`), and the longest track of the class
   to follow is the target (:func:`~uavcal_jax.track.associate.longest_track`), its length
   counted in boxes inside the image (a box cut by the border cannot be located), continued
   through identity breaks by the tracks that overlap its ends, and (with
   ``associate.reacquire``) after the target was out of view by the next track of its class
   to appear (:func:`~uavcal_jax.track.associate.followed_detections`);
2. each of its boxes is located (:class:`Localizer`): from the depth image (``depth0``) when
   the recording has one, else from the stereo pair's disparity (``cam1``), else not at all,
   with the reason; a box cut by the image border, or a frame without a VIO pose, is not
   located either;
3. the located points are filtered over every left frame (the filter predicts between
   detections, :func:`uavcal_jax.track.filter.run_filter`). A class with a box model
   (:data:`~uavcal_jax.pipeline.run_config.CLASS_HALF_SIZE_M`) is located at its front
   surface and moved to the centre of the box seen so, at each candidate heading
   (:func:`centre_candidates`); the heading is tracked over time
   (:func:`uavcal_jax.track.heading.track_heading`), first from the boxes' shapes alone, then
   with the first pass's filtered velocity at the frame before as well (causal, as a live
   follower would have it), and the centres at that heading are filtered again.

Frames: ``T_WB`` the VIO's body pose (world = the VIO's gravity-aligned frame), ``T_BC`` the
left camera's extrinsic from the recording's calibration. Times in the filter are seconds
since the first left frame.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import time

import jax
import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.errors import DataError
from uavcal_jax.geometry.camera import PinholeRadtan, from_calibration
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.track import (
    REASONS,
    AssociateConfig,
    FilterOutput,
    assign_track_ids,
    contained_duplicates,
    cut_by_border,
    followed_detections,
    locate_box,
    longest_track,
)
from uavcal_jax.track.box_model import border_covariance, box_centre_candidates
from uavcal_jax.track.filter import run_filter
from uavcal_jax.track.heading import heading_from_velocity, heading_spread, track_heading
from uavcal_jax.track.stereo import locate_box_stereo, rectify_stereo

__all__ = ["LOCALISATION_MODES", "Localizer", "LocatedPoint", "TargetResult", "build_localizer",
           "centre_candidates", "centre_on_box", "filter_target", "track_target"]

#: How a recording's boxes are located: from its depth images, its stereo pair, or not at all.
LOCALISATION_MODES = ("depth", "stereo", "off")
#: Why a box was not located, besides the localisation's own :data:`uavcal_jax.track.REASONS`.
NO_POSE, BORDER = "no VIO pose at the frame", "box cut by the image border"


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
    """Locates left-image boxes of one recording (``mode`` one of :data:`LOCALISATION_MODES`;
    ``reason`` says why it is off). Build it with :func:`build_localizer`."""

    def __init__(self, sequence: Sequence, config: RunConfig, mode: str, reason: str = ""):
        self.mode, self.reason = mode, reason
        self._config = config
        self._extent = config.detect.target_extent()
        cam0 = sequence.camera("cam0")
        self._left = cam0
        self._size = cam0.calibration.resolution
        self._T_BC = np.asarray(cam0.calibration.T_BS, np.float64)
        #: the left camera's model
        self.camera = from_calibration(cam0.calibration)
        self._locate_cut = (config.detect.locate_cut
                            and config.detect.target_half_size() is not None)
        self._depth = sequence.depth.get("depth0")
        self._depth_index = {} if self._depth is None else {
            int(t): i for i, t in enumerate(self._depth.t_ns)}
        self._right = sequence.cameras.get("cam1")
        self._right_index = {} if self._right is None else {
            int(t): i for i, t in enumerate(self._right.t_ns)}
        self._rect = None
        if mode == "stereo":
            self._rect = rectify_stereo(self.camera, from_calibration(self._right.calibration),
                                        self._T_BC, self._right.calibration.T_BS)

    def cut_by_border(self, box) -> bool:
        """The box reaches within ``detect.border_px`` of the image border."""
        return cut_by_border(box, self._size, self._config.detect.border_px)

    def can_locate(self, box) -> bool:
        """A box can be located: inside the image, or cut by its border with
        ``detect.locate_cut`` on and a class with a box model, which is cut there as well
        (:data:`~uavcal_jax.pipeline.run_config.CLASS_HALF_SIZE_M`)."""
        return self._locate_cut or not self.cut_by_border(box)

    def locate(self, frame: int, box, T_WB: np.ndarray | None) -> LocatedPoint:
        """The world point of ``box`` (4,) in left frame ``frame`` seen from pose ``T_WB``
        (4, 4) (``None``: no pose)."""
        nan = LocatedPoint(np.full(3, np.nan), np.full((3, 3), np.nan), self.reason)
        if self.mode == "off":
            return nan
        if T_WB is None or not np.all(np.isfinite(T_WB)):
            return dataclasses.replace(nan, reason=NO_POSE)
        if not self.can_locate(box):
            return dataclasses.replace(nan, reason=BORDER)
        t_ns = int(self._left.t_ns[frame])
        cfg = self._config.locate
        if self.mode == "depth":
            i = self._depth_index.get(t_ns)
            if i is None:
                return dataclasses.replace(nan, reason="no depth image at the frame")
            out = locate_box(np.asarray(box, np.float32), self._depth.load(i), self.camera,
                             self._T_BC, T_WB, self._extent, cfg)
        else:
            j = self._right_index.get(t_ns)
            if j is None:
                return dataclasses.replace(nan, reason="no right image at the frame")
            out = locate_box_stereo(box, self._left.load(frame), self._right.load(j), self._rect,
                                    self._T_BC, T_WB, self._extent, cfg, self._config.stereo)
        reason = REASONS[int(out.reason)]
        return LocatedPoint(np.asarray(out.point, np.float64),
                            np.asarray(out.covariance, np.float64), reason,
                            np.asarray(T_WB, np.float64) @ self._T_BC, np.asarray(box, np.float64))


def build_localizer(sequence: Sequence, config: RunConfig) -> Localizer:
    """The recording's :class:`Localizer`: ``depth`` with a ``depth0`` stream, else ``stereo``
    with a ``cam1``, else ``off`` with the reason."""
    if "depth0" in sequence.depth:
        return Localizer(sequence, config, "depth")
    if "cam1" in sequence.cameras:
        try:
            return Localizer(sequence, config, "stereo")
        except ValueError as err:  # a rig stereo matching cannot use
            return Localizer(sequence, config, "off", f"localisation off: {err}")
    return Localizer(sequence, config, "off", "localisation off: the recording has no depth "
                     "image (depth0) and no right camera (cam1)")


@dataclasses.dataclass(frozen=True)
class TargetResult:
    """The followed target over the recording's ``T`` left frames.

    Attributes:
        class_name, class_id: the class followed.
        track_id: the followed track (``None``: no detection of the class).
        track_ids: per left frame, the track id of each detection (``None``: not detected;
            -1: a part of a larger box, :func:`~uavcal_jax.track.associate.contained_duplicates`).
        boxes: (T, 4) the followed track's box per frame (NaN where it has none).
        scores: (T,) its score (NaN where none).
        raw_frames: (R,) the frames whose box was located; raw_points (R, 3), raw_cov
            (R, 3, 3): the localisations (world, metres).
        not_located: ``{reason: count}`` of the followed boxes that were not located.
        filtered: :class:`~uavcal_jax.track.FilterOutput` (NumPy), one row per frame.
        localisation: ``mode`` (:data:`LOCALISATION_MODES`) and ``reason`` (why it is off).
        locate_ms: per located box, milliseconds (the first includes compilation).
        filter_ms: ``(first, second)`` call of the filter over all frames, milliseconds (the
            first compiles).
    """

    class_name: str
    class_id: int
    track_id: int | None
    track_ids: list[np.ndarray | None]
    boxes: np.ndarray
    scores: np.ndarray
    raw_frames: np.ndarray
    raw_points: np.ndarray
    raw_cov: np.ndarray
    not_located: dict[str, int]
    filtered: FilterOutput
    localisation: dict[str, str]
    locate_ms: np.ndarray
    filter_ms: tuple[float, float]


def _class_id(class_names, name: str) -> int:
    if name not in class_names:
        raise DataError(f"detect.follow_class={name!r} is not a class of the detector "
                        f"(its classes: {', '.join(class_names) or 'none'})")
    return list(class_names).index(name)


def filter_target(times_s: np.ndarray, raw_frames: np.ndarray, raw_points: np.ndarray,
                  raw_cov: np.ndarray, config: RunConfig, timed: bool = True
                  ) -> tuple[FilterOutput, tuple]:
    """The filter over all ``T`` frames (times ``times_s`` (T,), seconds) with the raw
    localisations at ``raw_frames``; returns its output (NumPy) and, with ``timed``, the times
    of two calls in milliseconds (the first compiles, the second is the steady state; without,
    one call and no times)."""
    T = times_s.shape[0]
    z = np.zeros((T, 3))
    R = np.tile(np.eye(3), (T, 1, 1))
    valid = np.zeros(T, bool)
    z[raw_frames], R[raw_frames], valid[raw_frames] = raw_points, raw_cov, True
    ms = []
    for _ in range(2 if timed else 1):
        t0 = time.perf_counter()
        out = jax.block_until_ready(run_filter(times_s, z, R, valid, config.filter))
        ms.append(1e3 * (time.perf_counter() - t0))
    return FilterOutput(*(np.asarray(a) for a in out)), tuple(ms)


def centre_candidates(front: np.ndarray, T_WC: np.ndarray, boxes: np.ndarray,
                      camera: PinholeRadtan, half_size, config: RunConfig
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Front-surface points (R, 3), seen from the camera poses ``T_WC`` (R, 4, 4) in ``boxes``
    (R, 4) (pixel edges) of ``camera``: the centres
    (R, H, 3) of boxes with ``half_size`` (3,) metres at each candidate heading, and each
    one's shape mismatch (R, H) (:func:`uavcal_jax.track.box_model.box_centre_candidates`)."""
    fit = jax.vmap(box_centre_candidates, in_axes=(0, 0, None, 0, None, None))
    centres, mismatch = fit(front, T_WC, np.asarray(half_size, np.float64), boxes, camera,
                            config.locate)
    return np.asarray(centres, np.float64), np.asarray(mismatch, np.float64)


def centre_on_box(times_s: np.ndarray, raw_frames: np.ndarray, front: np.ndarray,
                  located_cov: np.ndarray, T_WC: np.ndarray, boxes: np.ndarray,
                  camera: PinholeRadtan, half_size, config: RunConfig
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The box model's centres (R, 3) and their covariances (R, 3, 3) for the front-surface
    points ``front`` (R, 3) located at ``raw_frames`` (R,) of the frames at ``times_s`` (T,)
    (covariances ``located_cov`` (R, 3, 3), camera poses ``T_WC`` (R, 4, 4), boxes
    ``boxes`` (R, 4) in ``camera``'s image): the heading tracked
    from the boxes' shapes, filtered, then tracked again with the filtered velocity of the
    frame before (the module docstring); the heading's spread, and for a box cut by the
    image's border what the border hides (:func:`~uavcal_jax.track.box_model.border_covariance`),
    are added to each covariance."""
    centres, mismatch = centre_candidates(front, T_WC, boxes, camera, half_size, config)
    rows, t_raw = np.arange(len(raw_frames)), times_s[raw_frames]
    located_cov = located_cov + np.stack([
        border_covariance(b, camera.resolution, T[:3, :3], half_size, config.detect.border_px)
        for b, T in zip(boxes, T_WC, strict=True)])

    def at_heading(velocity_heading):
        pick, belief = track_heading(t_raw, mismatch, velocity_heading, config.heading)
        return centres[rows, pick], located_cov + heading_spread(centres, belief, pick)

    points, cov = at_heading(np.full(len(raw_frames), np.nan))  # the shapes alone
    first, _ = filter_target(times_s, raw_frames, points, cov, config, timed=False)
    heading = heading_from_velocity(first.velocity, config.heading.min_speed)
    return at_heading(np.concatenate([[np.nan], heading[:-1]])[raw_frames])  # causal


def _same_target(located, t_ns, config: AssociateConfig, frame_a: int, i_a: int, frame_b: int,
                 i_b: int) -> bool:
    """May box ``i_a`` of left frame ``frame_a`` and box ``i_b`` of frame ``frame_b`` be one
    target: both located (``located(frame, box)``) within ``same_radius + target_speed *
    gap``? (Yes where either cannot be located: nothing says otherwise.)"""
    a, b = located(frame_a, i_a), located(frame_b, i_b)
    if not (a.located and b.located):
        return True
    gap_s = abs(int(t_ns[frame_b]) - int(t_ns[frame_a])) * 1e-9
    reach = config.same_radius + config.target_speed * gap_s
    return bool(np.linalg.norm(np.asarray(b.point) - np.asarray(a.point)) <= reach)


def track_target(sequence: Sequence, detections: list[ImageDetections | None],
                 class_names, poses: list[np.ndarray | None], config: RunConfig,
                 localizer: Localizer) -> TargetResult:
    """Associate, choose, locate and filter (the module docstring's steps).

    Args:
        sequence: the recording (its left camera's frames index everything).
        detections: per left frame, the detections (score-thresholded), or ``None`` where the
            detector did not run.
        class_names: the detector's classes.
        poses: per left frame, the VIO's ``T_WB`` (4, 4), or ``None`` without a pose.
        config: the run's settings.
        localizer: :func:`build_localizer`'s.

    Raises:
        DataError: ``detect.follow_class`` is not one of ``class_names``.
    """
    class_id = _class_id(class_names, config.detect.follow_class)
    cam0 = sequence.camera("cam0")
    T = len(cam0)
    locate_ms: list[float] = []

    @functools.cache
    def located(frame: int, i: int) -> LocatedPoint:
        """Detection ``i`` of left frame ``frame`` located, once (association, the part check
        and the chain ask for the same boxes)."""
        t0 = time.perf_counter()
        out = localizer.locate(frame, detections[frame].boxes[i], poses[frame])
        locate_ms.append(1e3 * (time.perf_counter() - t0))
        return out

    same = functools.partial(_same_target, located, cam0.t_ns, config.associate)
    ran = [k for k in range(T) if detections[k] is not None]
    # a part of a target boxed beside the whole is not a target of its own; another target
    # seen past it, inside its box, is
    kept = [np.flatnonzero(contained_duplicates(
        detections[k].boxes, detections[k].classes, config.associate.merge_contained,
        lambda i, j, k=k: detections[k].classes[j] != class_id or same(k, i, k, j)))
        for k in ran]
    boxes_ran = [detections[k].boxes[i] for k, i in zip(ran, kept, strict=True)]
    classes_ran = [detections[k].classes[i] for k, i in zip(ran, kept, strict=True)]

    def same_ran(k_a: int, i_a: int, k_b: int, i_b: int) -> bool:
        """:func:`_same_target` for box ``i`` of detected frame ``k`` (the kept boxes)."""
        if classes_ran[k_b][i_b] != class_id:
            return True  # only the class followed is located
        return same(ran[k_a], int(kept[k_a][i_a]), ran[k_b], int(kept[k_b][i_b]))

    ids_ran = assign_track_ids(boxes_ran, classes_ran, config.associate, same_ran)
    track_ids: list[np.ndarray | None] = [None] * T
    for k, ids, index in zip(ran, ids_ran, kept, strict=True):
        track_ids[k] = np.full(len(detections[k].boxes), -1, np.int64)
        track_ids[k][index] = ids
    inside = [np.array([localizer.can_locate(b) for b in frame], bool) for frame in boxes_ran]
    chosen = longest_track(ids_ran, classes_ran, class_id, inside)
    if chosen is None:  # every box of the class is cut by the border: follow it anyway
        chosen = longest_track(ids_ran, classes_ran, class_id)
    boxes, scores = np.full((T, 4), np.nan), np.full(T, np.nan)
    raw_frames, points, covs, views, seen_boxes = [], [], [], [], []
    not_located: collections.Counter = collections.Counter()
    if chosen is not None:
        pick = followed_detections(ids_ran, boxes_ran, classes_ran, chosen, config.associate,
                                   same_ran)
        for k, i, index in zip(ran, pick, kept, strict=True):
            if i < 0:
                continue
            i = int(index[i])
            boxes[k], scores[k] = detections[k].boxes[i], detections[k].scores[i]
            point = located(k, i)
            if point.located:
                raw_frames.append(k)
                points.append(point.point)
                covs.append(point.covariance)
                views.append(point.T_WC)
                seen_boxes.append(point.box)
            else:
                not_located[point.reason] += 1
    times_s = (cam0.t_ns - cam0.t_ns[0]).astype(np.float64) * 1e-9
    raw_frames = np.asarray(raw_frames, np.int64)
    raw_points = np.asarray(points, np.float64).reshape(-1, 3)
    raw_cov = np.asarray(covs, np.float64).reshape(-1, 3, 3)
    half_size = config.detect.target_half_size()
    if half_size is not None and raw_frames.size:
        raw_points, raw_cov = centre_on_box(
            times_s, raw_frames, raw_points, raw_cov, np.asarray(views, np.float64),
            np.asarray(seen_boxes, np.float64), localizer.camera, half_size, config)
    filtered, filter_ms = filter_target(times_s, raw_frames, raw_points, raw_cov, config)
    return TargetResult(
        class_name=config.detect.follow_class, class_id=class_id, track_id=chosen,
        track_ids=track_ids, boxes=boxes, scores=scores, raw_frames=raw_frames,
        raw_points=raw_points, raw_cov=raw_cov, not_located=dict(not_located),
        filtered=filtered, localisation={"mode": localizer.mode, "reason": localizer.reason},
        locate_ms=np.asarray(locate_ms), filter_ms=filter_ms)
