"""What the estimator hands out per frame: the front end's :class:`TrackedFrame` (the back
end's input), the back end's :class:`FrameEstimate`, and the :class:`FlowSeed` the back end
publishes for the next frame's front end (:class:`~uavcal_jax.vio.estimator.StereoVio`)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.frontend import FrameFeatures

__all__ = ["FlowSeed", "FrameEstimate", "TrackedFrame"]


class FlowSeed(NamedTuple):
    """What the back end last published for the front end
    (:meth:`~uavcal_jax.vio.estimator.StereoVio.flow_seed`).

    Attributes:
        bias_gyro: (3,) rad/s, the newest gyro bias (zero before the first pose).
        velocity_body: (3,) m/s, the newest tracked frame's velocity in its body frame, or
            ``None`` (before the first solved window, after a reset, while coasting).
    """

    bias_gyro: np.ndarray
    velocity_body: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class FrameEstimate:
    """The estimate at one stereo frame.

    Attributes:
        t_ns: frame time, ns.
        state: the :class:`~uavcal_jax.vio.body_state.BodyState` of the IMU (body) frame, or
            ``None`` before the first initialisation and outside the IMU stream. Its fields
            read through ``rotation`` (3, 3) body-to-world, ``position`` (3,) m,
            ``velocity`` (3,) m/s, ``bias_gyro`` (3,) rad/s, ``bias_accel`` (3,) m/s^2 (NaN
            without a state) and ``has_pose``.
        status: ``waiting`` (not initialised, no pose), ``initialized`` (this frame opened a
            window), ``tracking`` (solved with landmarks), ``coasting`` (IMU propagation: no
            landmarks, or waiting to re-initialise after a reset) or ``reset`` (a failure
            check fired at this frame, or its IMU interval has a gap: its pose is the IMU
            prediction, the last good state held, or none outside the IMU stream).
        reason: why it reset (a :class:`~uavcal_jax.vio.failure.Failure` or
            :class:`~uavcal_jax.vio.imu_slice.ImuGap` value), or why it is a keyframe, or ``""``.
        keyframe: the frame stayed in the window as a keyframe.
        tracked, stereo: the front end's corners and stereo matches.
        landmarks: landmarks observed in the window after the solve.
        iterations: solver iterations.  cost: the solved window cost.
        rows: residual rows in use in the window (``cost / rows`` near 0.5 when consistent).
        timings: milliseconds (:class:`~uavcal_jax.vio.stage_timer.StageTimer`): ``frontend``,
            ``solve`` (insert, solve, prune), ``marginalize`` (the slide), ``total``.
    """

    t_ns: int
    state: BodyState | None
    status: str
    reason: str = ""
    keyframe: bool = False
    tracked: int = 0
    stereo: int = 0
    landmarks: int = 0
    iterations: int = 0
    cost: float = float("nan")
    rows: int = 0
    timings: dict = dataclasses.field(default_factory=dict)

    @property
    def has_pose(self) -> bool:
        return self.state is not None

    def _pose(self) -> BodyState:
        return self.state if self.state is not None else BodyState.unknown(self.t_ns)

    rotation = property(lambda self: self._pose().rotation)
    position = property(lambda self: self._pose().position)
    velocity = property(lambda self: self._pose().velocity)
    bias_gyro = property(lambda self: self._pose().bias_gyro)
    bias_accel = property(lambda self: self._pose().bias_accel)


@dataclasses.dataclass(frozen=True)
class TrackedFrame:
    """The front end's output for one frame
    (:meth:`~uavcal_jax.vio.estimator.StereoVio.track`), the back end's input.

    Attributes:
        t_ns: frame time, ns.  features: the tracker's
            :class:`~uavcal_jax.vio.frontend.FrameFeatures`.
        frontend_ms: milliseconds the stage took.
    """

    t_ns: int
    features: FrameFeatures
    frontend_ms: float
