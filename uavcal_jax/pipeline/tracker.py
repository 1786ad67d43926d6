"""The online target stage: one left frame's detections, pose and images -> the followed
target, located, filtered, and the follow set-point. ``uavcal run`` folds it over a
recording's frames (:func:`uavcal_jax.pipeline.targets.track_target`); the closed loop
(:mod:`uavcal_jax.pipeline.closed_loop`) calls it once per rendered frame.

One :meth:`TargetTracker.step`, causal (it sees nothing after its frame):

1. association: the frame's detections, less the boxes of a part of a larger one
   (:func:`uavcal_jax.track.associate.contained_duplicates`), get track ids
   (:class:`uavcal_jax.track.associate.Associator`: Hungarian matching on IoU, ByteTrack's two
   rounds: a box scoring below ``detect.score_threshold`` only continues a track), two boxes
   of the class followed taken for one target only where they are located where it could
   have driven between them (``associate.same_radius + associate.target_speed * gap``);
2. the choice of the followed target (:class:`uavcal_jax.track.chain.FollowedChain`: the
   track of ``detect.follow_class`` seen inside the image longest so far, kept while seen,
   continued through identity breaks by an overlapping track, chosen anew once lost);
3. its box located (:class:`~uavcal_jax.pipeline.tracker_locate.Localizer`: depth or
   stereo); a class with a box model (:data:`~uavcal_jax.pipeline.run_config.CLASS_HALF_SIZE_M`)
   is located at its front surface and moved to the centre of the box seen so at the heading
   believed (:func:`uavcal_jax.track.heading.heading_step`: the box's shape, and the velocity
   at the frame before of a filter of the centres at the shapes' heading alone), the
   heading's spread and what the image border hides added to the covariance;
4. one step of the target filter (:func:`uavcal_jax.track.filter.filter_step`);
5. one step of the follow law (:func:`uavcal_jax.track.follow.follow_step`) from the pose's
   position (the last pose's where the frame has none), started at the first pose from its
   position and the left camera's heading.

Frames: ``T_WB`` the body pose in the pose's world (the VIO's, or the simulator's true one).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.tracker_locate import FrameSensors, Localizer, LocatedPoint
from uavcal_jax.track import UNSEEN, FilterOutput, Setpoint, contained_duplicates, follow_step
from uavcal_jax.track.associate import Associator
from uavcal_jax.track.box_model import border_covariance, box_centre_candidates
from uavcal_jax.track.chain import FollowedChain
from uavcal_jax.track.filter import filter_start, filter_step
from uavcal_jax.track.heading import (
    heading_from_velocity,
    heading_spread,
    heading_step,
    uniform_belief,
)

__all__ = ["TRACKER_STAGES", "TargetEstimate", "TargetTracker"]

#: The stages :attr:`TargetEstimate.ms` times.
TRACKER_STAGES = ("associate", "locate", "filter", "follow")


@dataclasses.dataclass(frozen=True)
class TargetEstimate:
    """One left frame's target.

    Attributes:
        track_ids: (N,) the track id of each detection (-1: a part of a larger box), or
            ``None`` where the detector did not run.
        track_id: the followed track (``None``: no box of it in the frame).
        box: (4,) its box (pixel edges; NaN where none); score: its score (NaN where none).
        located: its localisation (:class:`LocatedPoint`, at the box model's centre for a
            class with one), or ``None`` without a followed box.
        filtered: the filter's :class:`~uavcal_jax.track.FilterOutput` (NumPy, no frame axis).
        setpoint: the follow :class:`~uavcal_jax.track.Setpoint` (pose world; NumPy), or
            ``None`` before the first pose.
        ms: milliseconds per stage (:data:`TRACKER_STAGES`); locate_ms: per box located
            this frame (the association locates every box of the class that could continue a
            track, the followed box once).
    """

    track_ids: np.ndarray | None
    track_id: int | None
    box: np.ndarray
    score: float
    located: LocatedPoint | None
    filtered: FilterOutput
    setpoint: Setpoint | None
    ms: dict
    locate_ms: tuple


@dataclasses.dataclass
class _Frame:
    """A recent detected frame, for the same-target check on its boxes."""

    boxes: np.ndarray  # (N, 4) all detections
    T_WB: np.ndarray | None
    sensors: FrameSensors


class TargetTracker:
    """The online target stage (the module docstring). Its state: the association
    (:class:`~uavcal_jax.track.associate.Associator`), the followed chain
    (:class:`~uavcal_jax.track.chain.FollowedChain`), the heading belief, the filter's carry
    and the last set-point; localisations are kept per box (each box is located once).

    Args:
        config: the run's settings.
        class_id: ``detect.follow_class``'s id among the detector's classes.
        localizer: locates boxes (:func:`~uavcal_jax.pipeline.tracker_locate.build_localizer`).
    """

    def __init__(self, config: RunConfig, class_id: int, localizer: Localizer):
        self.config, self.class_id, self.localizer = config, class_id, localizer
        self.half_size = config.detect.target_half_size()
        self.associator = Associator(config.associate)
        self.chain = FollowedChain(class_id, config.associate)
        self.frames: dict[int, _Frame] = {}  # by detected frame (the association's count)
        self.times: dict[int, float] = {}  # seconds, by detected frame
        # by detected frame, the indices of its whole boxes (not parts): what the association
        # and the chain index (kept for every frame: a chain's last box may be long ago)
        self.kept: dict[int, np.ndarray] = {}
        self.points: dict[tuple[int, int], LocatedPoint] = {}  # (detected frame, box)
        # the heading beliefs: from the box shapes alone, and with the velocity as well
        self.shape_belief, self.belief, self.t_belief = uniform_belief(), uniform_belief(), None
        self.carry = None  # the filter's, from the first step
        self.shape_carry = None  # the filter of the shape-only centres (box model only)
        self.velocity_heading = np.nan  # of the shape filter's velocity after the last step
        self.setpoint: Setpoint | None = None
        self.start: Setpoint | None = None  # the first set-point (the first pose's)
        self.drone: np.ndarray | None = None  # the last pose's position
        self.t_last: float | None = None
        self._locate_ms: list[float] = []

    def step(self, t_s: float, detections: ImageDetections | None, T_WB: np.ndarray | None,
             sensors: FrameSensors) -> TargetEstimate:
        """One left frame at ``t_s`` seconds (increasing) with its ``detections`` (``None``:
        the detector did not run), the body pose ``T_WB`` (4, 4) (``None``: none) and its
        images ``sensors``."""
        self._locate_ms = []
        c0 = time.perf_counter()
        ids = pick = shape_only = None
        if detections is not None:
            ids, pick = self._associate(t_s, detections, T_WB, sensors)
        c1 = time.perf_counter()
        located, box, score, track_id = None, np.full(4, np.nan), np.nan, None
        if pick is not None and pick >= 0:
            box, score = np.asarray(detections.boxes[pick], np.float64), \
                float(detections.scores[pick])
            track_id = int(ids[pick])
            located, shape_only = self._centred(t_s, self._located(self.associator.frame, pick))
        c2 = time.perf_counter()
        filtered = self._filter(t_s, located, shape_only)
        c3 = time.perf_counter()
        setpoint = self._follow(t_s, filtered, T_WB)
        c4 = time.perf_counter()
        self.t_last = t_s
        ms = dict(zip(TRACKER_STAGES, 1e3 * np.diff([c0, c1, c2, c3, c4]), strict=True))
        return TargetEstimate(ids, track_id, box, score, located, filtered, setpoint, ms,
                              tuple(self._locate_ms))

    def _located(self, k: int, i: int) -> LocatedPoint:
        """Box ``i`` (of all the detections) of detected frame ``k``, located once."""
        point = self.points.get((k, i))
        if point is None:
            frame = self.frames[k]
            c0 = time.perf_counter()
            point = self.localizer.locate(frame.boxes[i], frame.T_WB, frame.sensors)
            self._locate_ms.append(1e3 * (time.perf_counter() - c0))
            self.points[(k, i)] = point
        return point

    def _same(self, k_a: int, i_a: int, k_b: int, i_b: int) -> bool:
        """May box ``i_a`` of detected frame ``k_a`` and box ``i_b`` of ``k_b`` (indices of
        all the detections) be one target: both located within ``same_radius + target_speed
        * gap``? (Yes where either cannot be located, or its frame is no longer kept.)"""
        if (k_a, i_a) not in self.points and k_a not in self.frames:
            return True
        a, b = self._located(k_a, i_a), self._located(k_b, i_b)
        if not (a.located and b.located):
            return True
        cfg = self.config.associate
        gap_s = abs(self.times[k_b] - self.times[k_a])
        reach = cfg.same_radius + cfg.target_speed * gap_s
        return bool(np.linalg.norm(b.point - a.point) <= reach)

    def _associate(self, t_s: float, det: ImageDetections, T_WB, sensors
                   ) -> tuple[np.ndarray, int]:
        """Steps 1 and 2: the frame's track ids (N,) and the followed box's index (-1: none)."""
        k = self.associator.frame + 1
        classes = np.asarray(det.classes, np.int64)
        self.frames[k] = _Frame(np.asarray(det.boxes, np.float64).reshape(-1, 4), T_WB, sensors)
        self.times[k] = t_s
        # a part of a target boxed beside the whole is not a target of its own; another
        # target seen past it, inside its box, is
        start = self.config.detect.score_threshold
        confident = np.asarray(det.scores, np.float64) >= start
        # a doubtful box continues a track it overlaps, or none: one that overlaps none is
        # dropped as a part without being located (the association would give it no id);
        # it still marks the boxes inside it as its parts (a track's part box continuing it
        # localised a car's part: on a closed-loop flight, 0.87 m off instead of 0.25)
        loose = ~confident & ~self.associator.could_continue(det.boxes, classes)
        # nor is a confident box a part of a doubtful one around it
        kept = np.flatnonzero(contained_duplicates(
            det.boxes, classes, self.config.associate.merge_contained,
            lambda i, j: loose[j] or ((confident[i] or not confident[j])
                                      and (classes[j] != self.class_id
                                           or self._same(k, i, k, j)))))
        self.kept[k] = kept

        def same_kept(k_a: int, i_a: int, k_b: int, i_b: int) -> bool:
            if classes[kept[i_b]] != self.class_id:  # k_b is this frame
                return True  # only the class followed is located
            return self._same(k_a, int(self.kept[k_a][i_a]), k_b, int(kept[i_b]))

        ids_kept = self.associator.step(det.boxes[kept], classes[kept], same_kept,
                                        np.asarray(det.scores)[kept], start)
        ids = np.full(len(classes), -1, np.int64)
        ids[kept] = ids_kept
        inside = np.array([self.localizer.can_locate(b) for b in det.boxes[kept]], bool)
        # a doubtful box that continues no track (id -1) is of no class the chain follows
        chained = np.where(ids_kept >= 0, classes[kept], -1)
        pick = self.chain.step(k, ids_kept, det.boxes[kept], chained, inside, same_kept)
        self._forget(k)
        return ids, (-1 if pick < 0 else int(kept[pick]))

    def _forget(self, k: int) -> None:
        """Drop the images of the frames no track or chain can reach back to any more."""
        cfg = self.config.associate
        for old in [j for j in self.frames if j < k - max(cfg.max_missed, cfg.stitch_gap) - 2]:
            del self.frames[old]

    def _centred(self, t_s: float, point: LocatedPoint
                 ) -> tuple[LocatedPoint, LocatedPoint | None]:
        """Step 3's box model: a located front-surface point moved to the box's centre at the
        heading believed, its covariance grown by the heading's spread and what the border
        hides; and the same at the heading of the box shapes alone (``None`` for a class
        without a box model or a point not located, which is returned unchanged)."""
        if self.half_size is None or not point.located:
            return point, None
        half = np.asarray(self.half_size, np.float64)
        centres, mismatch = box_centre_candidates(point.point, point.T_WC, half, point.box,
                                                  self.localizer.camera, self.config.locate)
        centres, mismatch = np.asarray(centres, np.float64), np.asarray(mismatch, np.float64)
        dt = 0.0 if self.t_belief is None else t_s - self.t_belief
        self.t_belief = t_s
        cov = point.covariance + border_covariance(point.box, self.localizer.camera.resolution,
                                                   point.T_WC[:3, :3], self.half_size,
                                                   self.config.detect.border_px)
        self.shape_belief = heading_step(self.shape_belief, dt, mismatch, np.nan,
                                         self.config.heading)
        self.belief = heading_step(self.belief, dt, mismatch, self.velocity_heading,
                                   self.config.heading)
        out = []
        for belief in (self.belief, self.shape_belief):
            chosen = int(np.argmax(belief))
            out.append(dataclasses.replace(
                point, point=centres[chosen],
                covariance=cov + heading_spread(centres, belief, chosen)))
        return out[0], out[1]

    def _filter(self, t_s: float, located: LocatedPoint | None,
                shape_only: LocatedPoint | None) -> FilterOutput:
        """Step 4 (NumPy output). For a class with a box model a second filter, of the centres
        at the shapes' heading alone, gives the velocity whose heading the next frame's step 3
        believes (filtering the velocity-informed centres instead would feed the heading back
        on itself: on a simulated V2_02 flight with three targets the filtered RMSE was 0.646 m
        so, 0.628 m with the second filter)."""
        if self.carry is None:
            dtype = jnp.asarray(np.zeros(1)).dtype
            self.carry = filter_start(t_s, dtype)
            self.shape_carry = filter_start(t_s, dtype) if self.half_size is not None else None
        self.carry, out = self._filter_step(self.carry, t_s, located)
        if self.shape_carry is not None:
            self.shape_carry, shape = self._filter_step(self.shape_carry, t_s, shape_only)
            self.velocity_heading = float(heading_from_velocity(
                shape.velocity[None], self.config.heading.min_speed)[0])
        return out

    def _filter_step(self, carry, t_s: float, located: LocatedPoint | None):
        valid = located is not None and located.located
        z = located.point if valid else np.zeros(3)
        R = located.covariance if valid else np.eye(3)
        carry, out = filter_step(carry, t_s, z, R, valid, self.config.filter)
        return carry, FilterOutput(*(np.asarray(a) for a in jax.device_get(out)))

    def _follow(self, t_s: float, filtered: FilterOutput, T_WB) -> Setpoint | None:
        """Step 5 (NumPy), ``None`` before the first pose."""
        if T_WB is not None and np.all(np.isfinite(T_WB)):
            self.drone = np.asarray(T_WB, np.float64)[:3, 3]
            if self.start is None:
                axis = np.asarray(T_WB, np.float64)[:3, :3] @ self.localizer.T_BC[:3, 2]
                self.start = self.setpoint = Setpoint(self.drone.copy(),
                                                      float(np.arctan2(axis[1], axis[0])))
        if self.setpoint is None:
            return None
        dt = 0.0 if self.t_last is None else t_s - self.t_last
        nxt = follow_step(self.setpoint, filtered.position, filtered.status != UNSEEN,
                          self.drone, dt, self.config.follow)
        self.setpoint = Setpoint(np.asarray(nxt.position, np.float64), float(nxt.yaw))
        return self.setpoint
