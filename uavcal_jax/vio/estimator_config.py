"""Configuration of the sliding-window estimator (:mod:`uavcal_jax.vio.estimator`): window
capacities, the initial prior, the solve budget and the failure limits. Frozen and hashable;
the front end's and the cost's settings are nested so one object describes a run."""

from __future__ import annotations

import dataclasses

from uavcal_jax.vio.config import CostConfig, SolverConfig
from uavcal_jax.vio.frontend_config import FrontendConfig, KeyframeConfig
from uavcal_jax.vio.marginalize import MarginalizeConfig
from uavcal_jax.vio.window import DEFAULT_KEYFRAMES

__all__ = ["EstimatorConfig", "FailureLimits", "InitialPrior"]


@dataclasses.dataclass(frozen=True)
class InitialPrior:
    """Standard deviations of the prior put on the first keyframe at (re-)initialisation.

    It fixes the gauge (position and yaw are unobservable to a VIO) and states what is known
    of the rest before any measurement: roll and pitch from the accelerometer, a velocity from
    the hover assumption (or the IMU propagation after a reset), biases within the sensor's
    turn-on spread.

    Attributes:
        position: m.  yaw: rad, about world z.  roll_pitch: rad.
        velocity: m/s.  bias_gyro: rad/s.  bias_accel: m/s^2.
    """

    position: float = 1e-3
    yaw: float = 1e-3
    roll_pitch: float = 0.05
    velocity: float = 0.5
    bias_gyro: float = 0.1
    bias_accel: float = 0.3


@dataclasses.dataclass(frozen=True)
class FailureLimits:
    """When the estimator declares the window failed and re-initialises (VINS-Fusion's
    ``failureDetection``, which it ships disabled; here it runs).

    Attributes:
        max_bias_gyro: rad/s, norm of a gyro bias estimate (VINS 1.0).
        max_bias_accel: m/s^2, norm of an accel bias estimate (VINS 2.5).
        max_translation_jump: m, the newest frame's solved position against its IMU
            prediction (VINS 5 m between solves; a prediction is a tighter reference).
        max_rotation_jump_deg: degrees, the same for the orientation (VINS 50).
        max_cost_per_residual: the solved cost divided by the number of residual rows in use;
            a consistent window sits near 0.5.
        min_landmarks: fewer active landmarks than this in a full window, for
            ``max_blind_frames`` consecutive frames, ends the window (IMU-only coasting
            before that).
        max_blind_frames: see ``min_landmarks``.
    """

    max_bias_gyro: float = 1.0
    max_bias_accel: float = 2.5
    max_translation_jump: float = 0.5
    max_rotation_jump_deg: float = 20.0
    max_cost_per_residual: float = 50.0
    min_landmarks: int = 8
    max_blind_frames: int = 200


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    """The stereo VIO estimator.

    Attributes:
        keyframes: window slots ``N`` (RPEOD eq. 6: 10).
        landmarks: landmark slots ``L``; new landmarks are skipped while all are used (on a
            simulated V1_02 flight: 200 in use on average, 357 at most, 296 at the 95th
            percentile with 400 slots).
        observations: observation slots ``M`` (a frame adds at most two per corner; the
            same flight: 1,165 on average, 1,466 at the 95th percentile); an observation that
            finds no free slot is not used. The solve's cost grows with ``M`` and ``L``.
        imu_samples: raw samples kept per IMU interval (their merge must fit: see
            ``max_keyframe_interval_s``).
        max_keyframe_interval_s: a frame is made a keyframe when the last keyframe is older
            than this (a hover has no parallax; the merged interval must fit ``imu_samples``).
        min_stereo_depth, max_stereo_depth: m; stereo triangulations outside are not used to
            start a landmark.
        min_init_landmarks: stereo landmarks the first frame needs to initialise.
        accel_init_s: seconds of accelerometer averaged for roll and pitch at start.
        prior: :class:`InitialPrior`.  limits: :class:`FailureLimits`.
        cost, solver, marginalize, frontend, keyframe: the nested stages' settings. The
            solver runs 3 Levenberg-Marquardt iterations per frame from the IMU-predicted warm
            start. With 2 the solve costs a third less and a simulated V1_02 flight keeps its
            ATE (1.80 cm against 1.66 cm with 4), but a window marginalised while still
            converging hands a biased velocity to the prior: over 20 black frames on the real
            micro slice the IMU-only drift grew from 1.6 cm (3 or 4 iterations) to 12 cm.
    """

    keyframes: int = DEFAULT_KEYFRAMES
    landmarks: int = 320
    observations: int = 1600
    imu_samples: int = 128
    max_keyframe_interval_s: float = 0.5
    min_stereo_depth: float = 0.2
    max_stereo_depth: float = 40.0
    min_init_landmarks: int = 15
    accel_init_s: float = 0.2
    prior: InitialPrior = InitialPrior()
    limits: FailureLimits = FailureLimits()
    cost: CostConfig = CostConfig()
    solver: SolverConfig = SolverConfig(max_iterations=3, ftol=1e-6)
    marginalize: MarginalizeConfig = MarginalizeConfig()
    frontend: FrontendConfig = FrontendConfig()
    keyframe: KeyframeConfig = KeyframeConfig()

    def __post_init__(self):
        if self.keyframes < 3:
            raise ValueError("keyframes must be >= 3")
        if self.landmarks < 1 or self.observations < 2:
            raise ValueError("landmarks and observations must be positive")
        if not 0 < self.min_stereo_depth < self.max_stereo_depth:
            raise ValueError("need 0 < min_stereo_depth < max_stereo_depth")
