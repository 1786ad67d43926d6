"""The stereo VIO's settings: one frozen tree, :class:`VioConfig`, and its resolution against a
recording's calibration.

The root holds the window capacities and the branches of every stage: the front end
(:class:`FrontendConfig`), the keyframe decision (:class:`KeyframeConfig`), the window cost
(:class:`CostConfig`), the structured solver (:class:`SolverConfig`), the marginalisation
(:class:`MarginalizeConfig`), the failure limits (:class:`FailureLimits`) and the initial prior
(:class:`InitialPrior`). Every default is here and only here; the ``uavcal vio`` command
overrides them with ``--set section.field=value`` (:func:`uavcal_jax.config.apply_overrides`)
and writes the resolved tree beside the trajectory. The dataclasses are frozen and hashable:
the cost and solver settings are static pytree metadata, so a jitted solve compiles once per
configuration.

Camera-dependent values come from the recording, never from a constant: ``cost.focal_px``
``None`` means "the left camera's ``fx``", filled in by :func:`resolve_camera` (which
:func:`~uavcal_jax.vio.run.run_vio` and :class:`~uavcal_jax.vio.estimator.StereoVio` call).
The pixel thresholds of the front end and the keyframe decision are instead expressed at
:data:`NOMINAL_FOCAL_PX`, a lens-independent unit.

One module, over 450 lines: one settings tree, most of its length the documentation of each
default and the reason for it; the resolution against a recording's rig (its camera, its
IMU noise: :func:`imu_noise`) belongs beside it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from uavcal_jax.data.sequence import CameraCalibration
from uavcal_jax.imu.noise import ImuNoise

__all__ = [
    "EQUALIZERS",
    "ESTIMATORS",
    "NOMINAL_FOCAL_PX",
    "OUTLIER_METHODS",
    "ROBUST_KERNELS",
    "CostConfig",
    "FailureLimits",
    "FrontendConfig",
    "InitialPrior",
    "KeyframeConfig",
    "MarginalizeConfig",
    "SolverConfig",
    "VioConfig",
    "imu_noise",
    "resolve_camera",
    "resolve_cost",
]

#: VINS-Fusion's ``FOCAL_LENGTH`` (460 px): the unit of the front end's and the keyframe
#: decision's pixel thresholds (RANSAC's epipolar distance, the keyframe parallax). Those
#: thresholds are normalised-coordinate distances times this nominal focal length, so they
#: are angles that mean the same on every lens; it is not any camera's focal length (the
#: window cost uses the real one, :attr:`CostConfig.focal_px`).
NOMINAL_FOCAL_PX = 460.0

#: Robust functions of the reprojection residual (see :mod:`uavcal_jax.vio.robust`).
ROBUST_KERNELS = ("huber", "cauchy", "none")
#: Frame-to-frame outlier rejection on undistorted points (see :class:`FrontendConfig`).
OUTLIER_METHODS = ("fundamental", "essential", "none")
#: Robust estimators of that rejection (see :class:`FrontendConfig`).
ESTIMATORS = ("usac", "ransac")
#: Image equalisation before tracking (see :class:`FrontendConfig`).
EQUALIZERS = ("histogram", "clahe", "none")


# --- front end -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FrontendConfig:
    """The optical-flow feature tracker (:class:`uavcal_jax.vio.frontend.FeatureTracker`).

    The defaults are VINS-Fusion's EuRoC settings (``config/euroc/euroc_stereo_imu_config.yaml``
    and ``feature_tracker.cpp``) where RPEOD (sec. 3.1) leaves them open; the re-detection
    threshold of 120 tracked corners is RPEOD's.

    Attributes:
        max_features: capacity of a frame's feature arrays and the most corners kept
            (VINS ``max_cnt``: 150).
        min_distance_px: corners are kept at least this far apart, pixels (VINS ``min_dist``).
        redetect_below: new corners are detected when fewer than this many are tracked
            (RPEOD sec. 3.1: 120).
        quality_level, block_size: ``cv2.goodFeaturesToTrack``'s Shi-Tomasi quality (relative
            to the best corner; VINS 0.01) and its derivative covariation block (pixels).
        lk_window_px: side of the square Lucas-Kanade window, pixels (VINS 21).
        lk_max_level: ``calcOpticalFlowPyrLK``'s ``maxLevel`` (VINS 3: the image plus three
            halvings).
        lk_iterations, lk_epsilon: the LK stopping criteria (OpenCV's and VINS's 30, 0.01).
        predicted_max_level: ``maxLevel`` when a gyro prediction seeds the flow (VINS 1); when
            fewer than ``min_predicted_tracked`` corners survive, the flow is rerun from scratch
            with ``lk_max_level`` as VINS does.
        min_predicted_tracked: see ``predicted_max_level`` (VINS 10).
        retry_unseeded: the corners a seeded pass loses are tracked again from scratch on
            ``lk_max_level`` levels (VINS drops them). The gyro seed holds only the rotation;
            on fast flights near a surface the translation's flow outruns the seeded search
            (a simulated 7 m/s flight 1.8 m under a ceiling, 376 px wide: 35 of 72 corners
            tracked on per frame without the retry, 53 with it, none of them wrong by 2 px).
        seed_translation_flow: the seed adds each corner's flow of the previous frame that
            the gyro rotation did not explain (its translation's flow, which changes little
            in one frame at a steady speed).
        fb_threshold_px: a track is kept when tracking it back lands within this distance of
            where it started, pixels (VINS 0.5).
        border_px: tracks closer than this to the image edge are dropped (VINS 1).
        exclude_margin: the boxes a caller excludes (moving objects: the detector's boxes,
            :meth:`FeatureTracker.track`'s ``exclude``) grow by this fraction of their size on
            each side before tracks in them are dropped and no corner is detected there (the
            object moves and its box lags or misses its edge by a few pixels).
        outlier_method: ``"fundamental"`` (RANSAC on the fundamental matrix of undistorted
            points on a virtual pinhole of focal :data:`NOMINAL_FOCAL_PX`, as VINS-Mono's
            ``rejectWithF``), ``"essential"`` (RANSAC on the essential matrix of normalised
            points) or ``"none"``.
        estimator: ``"usac"`` (OpenCV's USAC: RANSAC with local optimisation; the 8-point
            solver for the fundamental matrix, the 5-point one for the essential matrix) or
            ``"ransac"`` (OpenCV's classic RANSAC, VINS's ``FM_RANSAC``). On 150 synthetic
            matches with 0.2 px noise and a 1 px threshold the classic one drops 6-14 % of
            the correct matches (its answer is the best minimal sample, never refined);
            USAC keeps all of them, rejects the same outliers, and is no slower.
        ransac_threshold_px: RANSAC's epipolar distance on the virtual pinhole, pixels at
            :data:`NOMINAL_FOCAL_PX` (VINS ``F_threshold``: 1).
        imu_consensus: when the motion is predicted (the gyro's rotation and the back end's
            velocity), a RANSAC consensus that the prediction does not explain is replaced by
            the consensus of the rest when the prediction explains the rest: a moving object
            filling the view (a followed car the detector does not box, seen 3 m ahead from
            a low flight) outvotes the static scene, and the window then sees only it
            (:func:`uavcal_jax.vio.match_checks.imu_consistent_inliers`).
        imu_consensus_px: the consensus is not explained when its tracks' median distance to
            their predicted epipolar lines exceeds this, pixels at :data:`NOMINAL_FOCAL_PX`...
        imu_consensus_ratio: ... and the rest's median is below this fraction of it.
        imu_gate_factor, imu_gate_px: then a track of the consensus leaves it when its
            distance exceeds both this many times the consensus's median and this many pixels
            (at :data:`NOMINAL_FOCAL_PX`).
        ransac_confidence: RANSAC's confidence (VINS 0.99).
        stereo: track the left corners into the right image when one is given.
        stereo_epipolar_px: a left-right match is kept when its symmetric distance to the
            epipolar lines of the known extrinsic is at most this, in normalised units times
            the left focal length (pixels); ``math.inf`` switches the check off (VINS-Fusion
            has none; its back end sees every forward-backward-consistent match).
        stereo_seed_disparity: a corner matched left-to-right in the previous frame starts
            its stereo LK at that frame's disparity on ``predicted_max_level`` levels (as a
            gyro-seeded temporal track; fewer than ``min_predicted_tracked`` survivors rerun
            it from scratch); ``False``: every corner searches all ``lk_max_level`` levels.
        equalize: how both images are equalised before tracking. ``"clahe"`` is VINS-Mono's
            ``equalize: 1`` on EuRoC (``clahe_clip`` and ``clahe_tiles``: its clip limit and
            tile grid, VINS 3.0 and 8x8); ``"histogram"`` is ``cv2.equalizeHist``; ``"none"``
            tracks raw intensities. Lucas-Kanade assumes constant brightness and EuRoC's two
            cameras differ in gain (mean 145 vs 130 in V1_01), so without equalisation only
            ~35 of 150 corners find their stereo match there; both equalisers give ~75. The
            default is ``"histogram"``: on the V1_01 micro slice it matched slightly more
            corners (77 vs 73 per frame, the same epipolar residuals) and the tracker ran
            ~30 % faster per frame, CLAHE's amplified fine texture making LK iterate longer.
        min_contrast: a left image whose intensity standard deviation (gray levels, before
            equalisation) is below this is textureless -- black, blank, lens covered: every
            track ends there and no corner is detected, since equalisation would turn its
            sensor noise into corners that track nothing.
    """

    max_features: int = 150
    min_distance_px: float = 30.0
    redetect_below: int = 120
    quality_level: float = 0.01
    block_size: int = 3
    lk_window_px: int = 21
    lk_max_level: int = 3
    lk_iterations: int = 30
    lk_epsilon: float = 0.01
    predicted_max_level: int = 1
    min_predicted_tracked: int = 10
    retry_unseeded: bool = True
    seed_translation_flow: bool = True
    fb_threshold_px: float = 0.5
    border_px: int = 1
    exclude_margin: float = 0.1
    outlier_method: str = "fundamental"
    estimator: str = "usac"
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.99
    imu_consensus: bool = True
    imu_consensus_px: float = 2.0
    imu_consensus_ratio: float = 0.5
    imu_gate_factor: float = 4.0
    imu_gate_px: float = 4.0
    stereo: bool = True
    stereo_epipolar_px: float = 1.5
    stereo_seed_disparity: bool = True
    equalize: str = "histogram"
    clahe_clip: float = 3.0
    clahe_tiles: int = 8
    min_contrast: float = 2.0

    def __post_init__(self):
        if self.outlier_method not in OUTLIER_METHODS:
            raise ValueError(f"outlier_method must be one of {OUTLIER_METHODS}, "
                             f"got {self.outlier_method!r}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if self.equalize not in EQUALIZERS:
            raise ValueError(f"equalize must be one of {EQUALIZERS}, got {self.equalize!r}")
        if self.max_features < 1 or not 0 <= self.redetect_below <= self.max_features:
            raise ValueError("need max_features >= 1 and 0 <= redetect_below <= max_features")
        if self.lk_window_px < 3 or self.lk_window_px % 2 == 0:
            raise ValueError("lk_window_px must be an odd number >= 3")
        positive = (self.min_distance_px, self.fb_threshold_px, self.ransac_threshold_px,
                    self.stereo_epipolar_px, self.quality_level)
        if not all(v > 0 for v in positive) or math.isnan(sum(positive)):
            raise ValueError("distances, thresholds and quality level must be positive")


@dataclasses.dataclass(frozen=True)
class KeyframeConfig:
    """The keyframe decision (:func:`uavcal_jax.vio.keyframes.keyframe_decision`).

    Attributes:
        min_parallax_px: a frame is a keyframe when the mean rotation-compensated parallax of
            the features it shares with the last keyframe reaches this, in pixels at
            :data:`NOMINAL_FOCAL_PX` (VINS ``keyframe_parallax``: 10), so the threshold does
            not depend on the lens.
        min_tracked: a frame with fewer valid features than this is a keyframe (VINS: 20).
        min_common: a frame sharing fewer features than this with the last keyframe is a
            keyframe (VINS' ``long_track_num < 40``).
        max_rotation_deg: a frame turned more than this from the last keyframe (by the gyro)
            is a keyframe. A turn on the spot has no compensated parallax, so VINS' rules
            give a keyframe only every ``max_keyframe_interval_s`` while the view sweeps
            past: on the demo's flight (seed 9, 0.9 rad/s for 2 s) the window then spanned
            5 s, its cost grew tenfold and the outlier check reset it (``uavcal run``: ATE
            0.14 m, the car's filtered median 2.0 m). With 5 degrees (and
            ``rotation_min_interval_s``): ATE 0.030 m, 0.22 m; with 10 and 15 degrees the
            run was right or wrong by chance (ATE 0.024-0.064 m). ``bench_run.py`` measured
            no cost beyond its run-to-run spread.
        rotation_min_interval_s: the turn rule waits this long after the last keyframe. A
            follower yaws to face its target while it flies: keyframes from the turn on top
            of the parallax's shrank the window to about a second and the closed loop
            (``follow_closed_loop.py``) drifted (VIO ATE 0.59 m against 0.095 without the
            rule).
    """

    min_parallax_px: float = 10.0
    min_tracked: int = 20
    min_common: int = 40
    max_rotation_deg: float = 5.0
    rotation_min_interval_s: float = 0.25

    def __post_init__(self):
        if not self.min_parallax_px > 0:
            raise ValueError("min_parallax_px must be positive")
        if self.min_tracked < 0 or self.min_common < 0:
            raise ValueError("min_tracked and min_common must be >= 0")
        if not self.max_rotation_deg > 0:
            raise ValueError("max_rotation_deg must be positive")
        if not self.rotation_min_interval_s >= 0:
            raise ValueError("rotation_min_interval_s must be >= 0")


# --- back end ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CostConfig:
    """The window cost (RPEOD eqs. 7-9).

    Attributes:
        pixel_sigma: standard deviation of a feature position, pixels (VINS-Fusion: 1.5).
        focal_px: focal length that converts it to normalised coordinates,
            ``sigma / focal_px``: the left camera's ``fx``. ``None`` (the default) until
            :func:`resolve_cost` / :func:`resolve_camera` fills it in from the recording's
            calibration; the cost cannot be evaluated before.
        robust: ``"huber"`` (RPEOD eq. 9, VINS-Mono's paper), ``"cauchy"`` (VINS-Fusion's
            code) or ``"none"``; applied to the squared whitened reprojection error.
        robust_scale: the kernel's scale in whitened units (sigmas); 1 in both references.
        imu_jitter: variance added to the IMU residual covariance's diagonal before
            whitening. Needed (e.g. 1e-12) when the bias random walks are zero: the bias rows
            then have zero covariance and would not whiten.
        min_depth: depths (m) in the observing camera below this are clamped when
            projecting, so a point crossing the image plane mid-iteration stays finite.
    """

    pixel_sigma: float = 1.5
    focal_px: float | None = None
    robust: str = "huber"
    robust_scale: float = 1.0
    imu_jitter: float = 0.0
    min_depth: float = 1e-3

    def __post_init__(self):
        if self.robust not in ROBUST_KERNELS:
            raise ValueError(f"robust must be one of {ROBUST_KERNELS}, got {self.robust!r}")
        if not (self.pixel_sigma > 0 and self.robust_scale > 0):
            raise ValueError("pixel_sigma and robust_scale must be positive")
        if self.focal_px is not None and not self.focal_px > 0:
            raise ValueError("focal_px must be positive (or None: the left camera's fx)")

    @property
    def sqrt_info(self) -> float:
        """Whitening factor of a normalised-coordinate residual, ``focal_px / pixel_sigma``."""
        if self.focal_px is None:
            raise ValueError("CostConfig.focal_px is unresolved: resolve_cost() or "
                             "resolve_camera() sets it from the left camera's calibration")
        return self.focal_px / self.pixel_sigma


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """The structured Levenberg-Marquardt solve (:mod:`uavcal_jax.vio.solver`).

    The damped system is ``(H + lambda D) dx = -g`` with ``D = diag(H)`` (Marquardt's
    scaling, as Ceres), on frames and inverse depths alike.

    Attributes:
        max_iterations: iterations at most. The VIO runs 3 per frame from the IMU-predicted
            warm start. With 2 the solve costs a third less and a simulated V1_02 flight keeps
            its ATE (1.80 cm against 1.66 cm with 4), but a window marginalised while still
            converging hands a biased velocity to the prior: over 20 black frames on the real
            micro slice the IMU-only drift grew from 1.6 cm (3 or 4 iterations) to 12 cm.
            Solves from a cold start (tests, the self-calibration) set more.
        initial_damping: ``lambda`` at the first iteration; 0 with ``damping_factor`` 1 is
            plain Gauss-Newton.
        damping_factor: ``lambda`` is divided by it after an accepted step and multiplied by
            it after a rejected one.
        min_damping, max_damping: bounds of ``lambda``; the solve stops when it would exceed
            ``max_damping`` (no step decreases the cost).
        ftol: stop when an accepted step decreases the cost by less than ``ftol`` times it
            (the VIO's 1e-6; a converged-solution study sets 1e-12 or 0).
    """

    max_iterations: int = 3
    initial_damping: float = 1e-4
    damping_factor: float = 10.0
    min_damping: float = 1e-12
    max_damping: float = 1e8
    ftol: float = 1e-6


@dataclasses.dataclass(frozen=True)
class MarginalizeConfig:
    """Thresholds of the marginalisation (:mod:`uavcal_jax.vio.marginalize`; static,
    hashable).

    Both act on Jacobi-equilibrated matrices (unit diagonal), so they are relative and free of
    units; VINS-Fusion clips the raw eigenvalues at ``1e-8`` absolute, which with this window's
    information spread (diagonal from about 1e2 for a position to 1e12 for a bias random walk)
    would be scale dependent.

    Attributes:
        pinv_eps: eigenvalues of the eliminated block (keyframe 0, equilibrated) below this are
            treated as zero in its pseudo-inverse (an unconstrained direction carries nothing).
            The same relative threshold applies to a landmark's scalar information.
        prior_eps: eigenvalues of the reduced information (equilibrated) below this carry no
            information in the prior (``prior_from_information``'s ``eps``): the gauge
            directions, which the factors leave exactly unconstrained, fall below it.
    """

    pinv_eps: float = 1e-12
    prior_eps: float = 1e-10


# --- the estimator -------------------------------------------------------------------------


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
        max_velocity_jump: m/s, the newest frame's solved velocity against its IMU
            prediction.
        chi2_z, chi2_scale: the chi-square test of the window's cost
            (:func:`~uavcal_jax.vio.failure.chi2_bound`): ``2 cost`` above ``chi2_scale (rows +
            chi2_z sqrt(2 rows))`` fails it.
        max_cost_frames: more consecutive frames failing the chi-square test than this end
            the window; 0 (the default) switches the test off. On a simulated outdoor flight
            diverging from a bad start ``2 cost / rows`` rose from 0.05-0.2 to 1.5-8.6 while
            healthy simulated windows stay under 0.25; but on the real EuRoC micro slice a
            healthy window (ATE under 3 cm) reaches 7-130 for its last 15 frames (the whole
            window's cost, prior and IMU terms included, is no chi-square of the visual rows
            alone), so the test is opt-in until it is measured on the visual rows only.
        min_landmarks: fewer active landmarks than this in a full window, for
            ``max_blind_frames`` consecutive frames, ends the window (IMU-only coasting
            before that).
        max_blind_frames: see ``min_landmarks``.
        max_outlier_share, min_outlier_tracks, max_outlier_frames: the outlier test
            (:func:`~uavcal_jax.vio.failure.outlier_frames`): more than ``max_outlier_frames``
            consecutive frames, each with at least ``min_outlier_tracks`` observations of
            earlier landmarks of which the solve's prune rejected more than
            ``max_outlier_share``, end the window; ``max_outlier_frames = 0`` switches it off.
            It waits for the start check (``init_frames``). Healthy frames' rejected shares:
            at most 0.07 on a simulated V1_02 flight, 0.18 on a simulated 20 s outdoor_45_1
            flight, 0.39 on the real EuRoC micro slice (p99 0.35); with 1 s of track ids
            shuffled between frames, 0.98-1.0 from the first frame (reset 0.10 s in).
    """

    max_bias_gyro: float = 1.0
    max_bias_accel: float = 2.5
    max_translation_jump: float = 0.5
    max_rotation_jump_deg: float = 20.0
    max_cost_per_residual: float = 50.0
    max_velocity_jump: float = 1.0
    chi2_z: float = 3.1
    chi2_scale: float = 1.0
    max_cost_frames: int = 0
    min_landmarks: int = 8
    max_blind_frames: int = 200
    max_outlier_share: float = 0.5
    min_outlier_tracks: int = 20
    max_outlier_frames: int = 2


@dataclasses.dataclass(frozen=True)
class VioConfig:
    """The stereo VIO (:class:`~uavcal_jax.vio.estimator.StereoVio`): the root of the tree.

    Attributes:
        keyframes: window slots ``N`` (RPEOD eq. 6, VINS-Fusion's ``WINDOW_SIZE + 1``: 10).
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
        init_frames: frames of stereo odometry and IMU after a window opens that check its
            start while moving (:mod:`uavcal_jax.vio.motion_init`: gravity and velocity by
            linear alignment, no hover needed); below 3, no check. The window opens at once
            (levelled by the accelerometer mean and at rest at the first start, the
            IMU-propagated state after a reset), so every frame has a pose; a start that
            disagrees with the alignment by more than ``init_tilt_deg`` or ``init_velocity``
            is re-opened at the alignment (status ``initialized``, reason ``moving``). On a
            simulated outdoor flight accelerating at 3 m/s^2 the levelled start was 18 deg off
            in tilt and the run diverged (ATE 9.4 m over 41 m; 0.07 m with the check).
        init_tilt_deg, init_velocity: see ``init_frames``: degrees, m/s.
        accel_init_s: seconds of accelerometer averaged for roll and pitch at start.
        frontend: :class:`FrontendConfig`.  keyframe: :class:`KeyframeConfig`.
        cost: :class:`CostConfig` (its ``focal_px`` from the left camera:
            :func:`resolve_camera`).  solver: :class:`SolverConfig` (3 iterations per frame;
            see there).  marginalize: :class:`MarginalizeConfig`.
        limits: :class:`FailureLimits`.  prior: :class:`InitialPrior`.
        min_gyro_noise_density, min_accel_noise_density: rad/s/sqrt(Hz) and m/s^2/sqrt(Hz);
            the preintegration's white-noise densities are the recording's (its
            ``imu0/sensor.yaml``) or these, whichever is larger. A data sheet's densities are
            those of the sensor at rest; on a flying multirotor the rotors' vibration and the
            motion between samples add their own, and a window that trusts the sheet weighs
            the IMU far above the frames. The defaults are the real V1_01 IMU's, standing with
            its rotors on (0.0019 and 0.013, against the ADIS16448 sheet's 0.00017 and 0.002:
            ``experiments/sim_realism.py``). On a simulated 20 s V1_02 flight with EuRoC's
            vibration and IMU errors (the simulator's defaults) they took the ATE from 0.027 to
            0.012 m, and on an ideal IMU from 0.012 to 0.009 m. 0 keeps the recording's.
    """

    keyframes: int = 10
    landmarks: int = 320
    observations: int = 1600
    imu_samples: int = 128
    max_keyframe_interval_s: float = 0.5
    min_stereo_depth: float = 0.2
    max_stereo_depth: float = 40.0
    min_init_landmarks: int = 15
    init_frames: int = 10
    init_tilt_deg: float = 3.0
    init_velocity: float = 0.5
    accel_init_s: float = 0.2
    frontend: FrontendConfig = FrontendConfig()
    keyframe: KeyframeConfig = KeyframeConfig()
    cost: CostConfig = CostConfig()
    solver: SolverConfig = SolverConfig()
    marginalize: MarginalizeConfig = MarginalizeConfig()
    limits: FailureLimits = FailureLimits()
    prior: InitialPrior = InitialPrior()
    min_gyro_noise_density: float = 0.002
    min_accel_noise_density: float = 0.013

    def __post_init__(self):
        if self.keyframes < 3:
            raise ValueError("keyframes must be >= 3")
        if self.landmarks < 1 or self.observations < 2:
            raise ValueError("landmarks and observations must be positive")
        if not 0 < self.min_stereo_depth < self.max_stereo_depth:
            raise ValueError("need 0 < min_stereo_depth < max_stereo_depth")
        if self.min_gyro_noise_density < 0 or self.min_accel_noise_density < 0:
            raise ValueError("the noise density floors must be >= 0")


def imu_noise(config: VioConfig, recorded: ImuNoise) -> ImuNoise:
    """The noise model the VIO preintegrates with: the recording's, its white-noise densities
    raised to ``config``'s floors (per axis; a density already above its floor is kept)."""

    def floored(value, floor: float):
        if floor <= 0.0:
            return value
        out = np.maximum(np.asarray(value, np.float64), floor)
        return float(out) if out.ndim == 0 else out

    return dataclasses.replace(
        recorded,
        gyro_noise_density=floored(recorded.gyro_noise_density, config.min_gyro_noise_density),
        accel_noise_density=floored(recorded.accel_noise_density,
                                    config.min_accel_noise_density))


def resolve_cost(cost: CostConfig, left: CameraCalibration) -> CostConfig:
    """``cost`` with an unset ``focal_px`` taken from ``left``'s ``fx`` (pixels); a value set
    explicitly is kept."""
    if cost.focal_px is not None:
        return cost
    return dataclasses.replace(cost, focal_px=float(left.intrinsics[0]))


def resolve_camera(config: VioConfig, left: CameraCalibration) -> VioConfig:
    """``config`` with its camera-dependent values from the left camera's calibration
    (``cost.focal_px``: ``fx``, see :func:`resolve_cost`). Idempotent."""
    return dataclasses.replace(config, cost=resolve_cost(config.cost, left))
