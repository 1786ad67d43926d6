"""Detections -> the target to follow, located and filtered in the VIO's world frame, and the
follow set-points: the online :class:`~uavcal_jax.pipeline.tracker.TargetTracker` folded over
a recording's left frames (the middle of ``uavcal run``,
:func:`uavcal_jax.pipeline.run.run_pipeline`, after the VIO and the detector have run).

The tracker is causal: each frame's choice of target, heading and filtered estimate use the
frames up to it only, as a live follower has them. Its steps are in
:mod:`uavcal_jax.pipeline.tracker`; localisation (depth image, else stereo pair, else off) in
:mod:`uavcal_jax.pipeline.tracker_locate`.

Frames: ``T_WB`` the VIO's body pose (world = the VIO's gravity-aligned frame). Times are
seconds since the first left frame.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.tracker import TargetEstimate, TargetTracker
from uavcal_jax.pipeline.tracker_locate import (
    LOCALISATION_MODES,
    Localizer,
    build_localizer,
    recording_sensors,
)
from uavcal_jax.track import FilterOutput, Setpoint

__all__ = ["LOCALISATION_MODES", "TargetResult", "build_localizer", "class_id_of",
           "stack_estimates", "track_target"]


@dataclasses.dataclass(frozen=True)
class TargetResult:
    """The followed target over the recording's ``T`` left frames (the tracker's estimates,
    stacked).

    Attributes:
        class_name, class_id: the class followed.
        track_id: the track followed in the most frames (``None``: no detection of the
            class).
        track_ids: per left frame, the track id of each detection (``None``: not detected;
            -1: a part of a larger box, :func:`~uavcal_jax.track.associate.contained_duplicates`).
        boxes: (T, 4) the followed track's box per frame (NaN where it has none).
        scores: (T,) its score (NaN where none).
        raw_frames: (R,) the frames whose box was located; raw_points (R, 3), raw_cov
            (R, 3, 3): the localisations (world, metres).
        not_located: ``{reason: count}`` of the followed boxes that were not located.
        filtered: :class:`~uavcal_jax.track.FilterOutput` (NumPy), one row per frame.
        localisation: ``mode`` (:data:`LOCALISATION_MODES`) and ``reason`` (why it is off).
        setpoints: the follow :class:`~uavcal_jax.track.Setpoint`, position (T, 3) (VIO world)
            and yaw (T,) (frames before the first pose hold the first pose's set-point).
        locate_ms: per located box, milliseconds (the first includes compilation).
        filter_ms, follow_ms: (T,) per frame, milliseconds (the first compiles).
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
    setpoints: Setpoint
    locate_ms: np.ndarray
    filter_ms: np.ndarray
    follow_ms: np.ndarray


def class_id_of(class_names, name: str) -> int:
    """The id of class ``name`` among ``class_names``.

    Raises:
        DataError: ``name`` is not one of them."""
    if name not in class_names:
        raise DataError(f"detect.follow_class={name!r} is not a class of the detector "
                        f"(its classes: {', '.join(class_names) or 'none'})")
    return list(class_names).index(name)


def track_target(sequence: Sequence, detections: list[ImageDetections | None],
                 class_names, poses: list[np.ndarray | None], config: RunConfig,
                 localizer: Localizer) -> TargetResult:
    """:class:`~uavcal_jax.pipeline.tracker.TargetTracker` over every left frame.

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
    class_id = class_id_of(class_names, config.detect.follow_class)
    cam0 = sequence.camera("cam0")
    times_s = (cam0.t_ns - cam0.t_ns[0]).astype(np.float64) * 1e-9
    tracker = TargetTracker(config, class_id, localizer)
    sensors = recording_sensors(sequence)
    estimates = [tracker.step(float(times_s[k]), detections[k], poses[k], sensors(k))
                 for k in range(len(cam0))]
    return stack_estimates(estimates, tracker, config)


def stack_estimates(estimates: list[TargetEstimate], tracker: TargetTracker,
                    config: RunConfig) -> TargetResult:
    """The tracker's per-frame ``estimates`` as one :class:`TargetResult`."""
    T = len(estimates)
    followed = [e.track_id for e in estimates if e.track_id is not None]
    located = [(k, e.located) for k, e in enumerate(estimates)
               if e.located is not None and e.located.located]
    not_located = collections.Counter(e.located.reason for e in estimates
                                      if e.located is not None and not e.located.located)
    start = tracker.start or Setpoint(np.full(3, np.nan), np.nan)
    setpoints = [start if e.setpoint is None else e.setpoint for e in estimates]
    localizer = tracker.localizer
    return TargetResult(
        class_name=config.detect.follow_class, class_id=tracker.class_id,
        track_id=collections.Counter(followed).most_common(1)[0][0] if followed else None,
        track_ids=[e.track_ids for e in estimates],
        boxes=np.array([e.box for e in estimates], np.float64).reshape(T, 4),
        scores=np.array([e.score for e in estimates], np.float64),
        raw_frames=np.array([k for k, _ in located], np.int64),
        raw_points=np.array([p.point for _, p in located], np.float64).reshape(-1, 3),
        raw_cov=np.array([p.covariance for _, p in located], np.float64).reshape(-1, 3, 3),
        not_located=dict(not_located),
        filtered=FilterOutput(*(np.stack(a) for a in zip(*(e.filtered for e in estimates),
                                                          strict=True))),
        localisation={"mode": localizer.mode, "reason": localizer.reason},
        setpoints=Setpoint(np.array([s.position for s in setpoints], np.float64).reshape(T, 3),
                           np.array([s.yaw for s in setpoints], np.float64)),
        locate_ms=np.array([ms for e in estimates for ms in e.locate_ms], np.float64),
        filter_ms=np.array([e.ms["filter"] for e in estimates], np.float64),
        follow_ms=np.array([e.ms["follow"] for e in estimates], np.float64))
