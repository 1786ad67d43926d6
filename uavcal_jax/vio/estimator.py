"""The stereo VIO estimator, frame by frame: a front end and a back end that is a small state
machine over two phases.

* Front end (:meth:`StereoVio.track`): corners tracked by the optical flow, seeded by the gyro
  rotation since the previous frame (:mod:`uavcal_jax.vio.imu_slice`); the back end's last
  velocity (:meth:`StereoVio.flow_seed`) checks the outlier test's consensus.
* **No window** (``waiting`` before the first pose, ``coasting`` on the IMU after a reset): a
  frame with ``min_init_landmarks`` usable stereo matches opens a window (``initialized``)
  under a gauge prior. The first start is levelled by the accelerometer and at rest
  (:mod:`uavcal_jax.vio.initialize`), so the first frame has a pose; ``init_frames`` frames
  later the start is checked against gravity and velocity aligned from those frames' stereo
  odometry and IMU (:mod:`uavcal_jax.vio.start_check`) and the window re-opened there
  (reason ``moving``) when it was off (a body accelerating at the start). After a reset the
  estimator coasts on the IMU (reason ``reinit``) until the frames since align, and opens
  there: a re-initialisation while moving, no hover needed.
* **Window** (``tracking``, or ``coasting`` without landmarks): the frame is predicted by its
  IMU interval, tested for a keyframe (:mod:`uavcal_jax.vio.keyframes`, or the last keyframe
  older than ``max_keyframe_interval_s``), inserted, solved and pruned
  (:mod:`uavcal_jax.vio.sliding_window`), then checked (:mod:`uavcal_jax.vio.failure`). A
  failure or an IMU gap resets (``reset``) to no window, keeping an IMU-propagated state (after
  a failure, from the newest frame no failure test suspected) so the trajectory continues;
  otherwise the window slides as VINS-Mono and, when it first fills, refines the gyro bias
  from the keyframes' rotations.

A frame without features still enters the window with its IMU interval only. Output: one
:class:`~uavcal_jax.vio.frame_estimate.FrameEstimate` per frame;
:func:`~uavcal_jax.vio.run.run_vio` runs a whole sequence. The back end runs under
``jax.enable_x64(True)`` (switched on around its calls).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.sequence import CameraCalibration, ImuCalibration, ImuData
from uavcal_jax.errors import DataError
from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import VioConfig, imu_noise, resolve_camera
from uavcal_jax.vio.failure import Failure, FailureCounters
from uavcal_jax.vio.frame_estimate import FlowSeed, FrameEstimate, TrackedFrame
from uavcal_jax.vio.frontend import FeatureTracker, FrameFeatures
from uavcal_jax.vio.imu_slice import ImuGap, ImuStream
from uavcal_jax.vio.initialize import gravity_aligned_rotation
from uavcal_jax.vio.keyframes import body_to_camera_rotation, keyframe_decision
from uavcal_jax.vio.sliding_window import SlidingWindow
from uavcal_jax.vio.slots import stereo_depths
from uavcal_jax.vio.stage_timer import StageTimer
from uavcal_jax.vio.start_check import StartCheck
from uavcal_jax.vio.window import CalibParams, WindowProblem, WindowState

__all__ = ["PRUNE_DEPTH_FRACTION", "StereoVio"]

#: After each solve, landmarks whose depth in their anchor falls below ``min_stereo_depth``
#: times this leave the window (:func:`~uavcal_jax.vio.window_ops.prune`); new landmarks start
#: at ``min_stereo_depth`` or deeper.
PRUNE_DEPTH_FRACTION = 0.5


class StereoVio:
    """Stateful stereo-inertial odometry over one stream of frames.

    Args:
        left, right: the stereo cameras' calibrations (``T_BS``: camera to body (IMU)).
        imu_calibration: rate, IMU-to-body ``T_BS`` (must be the identity: the body frame is
            the IMU's) and noise model.
        imu: the whole IMU stream (samples already corrected for any known offset).
        config: :class:`~uavcal_jax.vio.config.VioConfig` (its camera-dependent values are
            resolved against ``left``: :func:`~uavcal_jax.vio.config.resolve_camera`).
    """

    def __init__(self, left: CameraCalibration, right: CameraCalibration,
                 imu_calibration: ImuCalibration, imu: ImuData,
                 config: VioConfig | None = None):
        self.config = cfg = resolve_camera(config if config is not None else VioConfig(), left)
        if not np.allclose(imu_calibration.T_BS, np.eye(4), atol=1e-9):
            raise DataError("the IMU's T_BS is not the identity: the estimator's body frame is "
                            "the IMU frame; express the cameras' T_BS relative to the IMU")
        self.tracker = FeatureTracker(left, right, cfg.frontend)
        self.noise = imu_noise(cfg, imu_calibration.noise)
        self.imu = ImuStream(imu, imu_calibration.rate_hz, cfg.imu_samples)
        T = np.stack([np.asarray(left.T_BS, np.float64), np.asarray(right.T_BS, np.float64)])
        self.T_C0C1 = np.linalg.inv(T[0]) @ T[1]
        self.R_BC0 = T[0, :3, :3]
        self.T_BC0 = T[0]
        self._start: StartCheck | None = None  # the check of an unconfirmed start
        with jax.enable_x64(True):
            self.params = CalibParams(jnp.zeros(6), jnp.asarray(T[:, :3, :3]),
                                      jnp.asarray(T[:, :3, 3]))
        self.resets = 0
        self._new_window()  # self.window and its failure counts
        self._last_good: BodyState | None = None
        # the newest solved state no failure test suspected (every count at zero): a reset
        # coasts from it, not from the frames that led to the failure
        self._trusted: BodyState | None = None
        #: ``None`` or a callable ``(t_ns, state, problem, params)`` handed each full window
        #: solved on a good frame (no failure, enough landmarks), before it slides: for
        #: studies of the window itself (:mod:`uavcal_jax.vio.selfcalib`). Called in
        #: :meth:`update`'s thread; the arrays are immutable, so keeping them costs no copy.
        self.window_sink: Callable[[int, WindowState, WindowProblem, CalibParams], None] | None
        self.window_sink = None
        # the front end's own view: its previous frame; and the newest gyro bias and velocity
        # the back end published, which seed the flow (read through flow_seed(), a snapshot,
        # never by a front end running concurrently with update())
        self._fe_t_ns: int | None = None
        self._published = FlowSeed(np.zeros(3), None)

    def process(self, t_ns: int, img_left: np.ndarray | None, img_right: np.ndarray | None,
                exclude: np.ndarray | None = None) -> FrameEstimate:
        """Process one stereo frame (either image may be ``None``: a dropped frame):
        :meth:`track` (seeded by the newest published :meth:`flow_seed`) then :meth:`update`."""
        return self.update(self.track(t_ns, img_left, img_right, self.flow_seed(), exclude))

    def flow_seed(self) -> FlowSeed:
        """A copy of the newest gyro bias and body velocity :meth:`update` published: what a
        caller hands :meth:`track` to seed the flow."""
        seed = self._published
        return FlowSeed(seed.bias_gyro.copy(),
                        None if seed.velocity_body is None else seed.velocity_body.copy())

    def track(self, t_ns: int, img_left: np.ndarray | None, img_right: np.ndarray | None,
              seed: FlowSeed, exclude: np.ndarray | None = None) -> TrackedFrame:
        """The front end of one frame: the gyro rotation since the previous frame, corrected
        by ``seed.bias_gyro``, seeds the optical flow; with ``seed.velocity_body`` the
        predicted motion also checks the outlier test's consensus. Touches only the tracker
        and the front end's own state, so it may run in another thread than :meth:`update`
        (one frame ahead of it: OpenCV and XLA release the GIL). The seed is an argument, not
        read here, so that which estimate seeds the flow is decided by the caller (a snapshot
        taken when the task is handed out, :meth:`flow_seed`) and not by thread timing.
        ``exclude``: (M, 4) left-image boxes of moving objects that no track may lie in
        (:meth:`~uavcal_jax.vio.frontend.FeatureTracker.track`)."""
        t_ns = int(t_ns)
        t0 = time.perf_counter()
        bias_gyro = np.asarray(seed.bias_gyro, np.float64).reshape(3)
        R_gyro = t_body = None
        if self._fe_t_ns is not None and t_ns > self._fe_t_ns:
            R_gyro = self.imu.gyro_rotation(self._fe_t_ns, t_ns, bias_gyro)
            if seed.velocity_body is not None:
                t_body = np.asarray(seed.velocity_body, np.float64) * (
                    (t_ns - self._fe_t_ns) * 1e-9)
        self._fe_t_ns = t_ns
        feats = self.tracker.track(t_ns * 1e-9, img_left, img_right, R_gyro, exclude, t_body)
        return TrackedFrame(t_ns, feats, 1e3 * (time.perf_counter() - t0))

    def update(self, frame: TrackedFrame) -> FrameEstimate:
        """The back end of one frame (:meth:`track`'s output, in time order)."""
        timer = StageTimer(frame.frontend_ms)
        with jax.enable_x64(True):
            if self.window.slots.newest < 0:
                est = self._open_window(frame.t_ns, frame.features, timer)
            else:
                est = self._track_frame(frame.t_ns, frame.features, timer)
        if est.has_pose:
            # the velocity only from a solved window: a start at rest or a coast does not
            # know it well enough to judge the front end's tracks
            velocity = (np.asarray(est.rotation, np.float64).T @ np.asarray(est.velocity)
                        if est.status == "tracking" else None)
            self._published = FlowSeed(np.array(est.bias_gyro, np.float64), velocity)
        return est

    def _measurements(self, feats: FrameFeatures, depths: tuple) -> tuple:
        """The window's landmark and observation updates of ``feats`` (slots taken), from its
        stereo ``depths`` (:func:`~uavcal_jax.vio.slots.stereo_depths`)."""
        depth, usable = depths
        return self.window.slots.measurements(feats, depth, usable,
                                              self.config.frontend.max_features)

    def _track_frame(self, t_ns: int, feats: FrameFeatures, timer: StageTimer
                     ) -> FrameEstimate:
        """The window phase: predict, decide the keyframe, insert and solve, check, slide."""
        cfg, window, slots = self.config, self.window, self.window.slots
        prev = window.newest_state()
        iv = self.imu.slice(prev.t_ns, t_ns)
        if iv.gap is not None:
            return self._reset(iv.gap, t_ns, None, timer, feats)
        pim, pred = prev.propagate(iv.samples, self.noise, t_ns)
        R_kf_cur = body_to_camera_rotation(slots.kf_rotation.T @ pred.rotation, self.R_BC0)
        elapsed_s = (t_ns - slots.last_keyframe_time()) * 1e-9
        dec = keyframe_decision(slots.kf_features.ids, slots.kf_features.xy, feats.ids, feats.xy,
                                feats.mask, R_kf_cur, cfg.keyframe, elapsed_s)
        is_kf, reason = dec.is_keyframe, dec.reason
        if not is_kf and elapsed_s > cfg.max_keyframe_interval_s:
            is_kf, reason = True, "interval"

        depths = stereo_depths(feats, self.T_C0C1, cfg.min_stereo_depth, cfg.max_stereo_depth)
        updates = self._measurements(feats, depths)
        info, active, est = window.insert_solve(
            pred, pim, self.imu.full_row(iv.samples), updates, is_kf,
            cfg.min_stereo_depth * PRUNE_DEPTH_FRACTION)
        timer.lap("solve")
        cost = float(info.cost_final)
        # the velocity and outlier tests wait for the start check to end
        failure = self._failures.check(est, pred, cost, slots.rows, active, updates,
                                       slots.observation_used, cfg.limits,
                                       settled=self._start is None)
        if failure is not None:
            return self._reset(failure, t_ns, pred, timer, feats)

        if (self.window_sink is not None and slots.filled_once
                and active >= cfg.limits.min_landmarks):
            self.window_sink(t_ns, window.state, window.problem, window.params)
        if is_kf:
            slots.kf_features, slots.kf_rotation = feats, est.rotation
        window.slide()
        if not slots.filled_once and slots.newest >= cfg.keyframes - 2:
            window.refine_gyro_bias()
        timer.lap("marginalize")
        self._last_good = est
        counts = self._failures
        if counts.blind == counts.cost_excess == counts.outliers == 0:
            self._trusted = est
        check = self._start
        if check is not None and cfg.init_frames >= 3:
            # the start check: once the frames align it ends, re-opening the window at the
            # aligned state when the solved one is off (a start at rest on a moving body);
            # it ends too after 3 * init_frames frames without an alignment
            check.add(t_ns, feats, depths)
            start = check.align(est)
            if start is not None or check.exhausted:
                self._start = None
            if start is not None and check.disagrees(start, est):
                self._new_window()
                return self._open(t_ns, start, "moving", feats, depths, timer)
        status = "tracking" if active >= cfg.limits.min_landmarks else "coasting"
        return FrameEstimate(t_ns, est, status, reason, keyframe=is_kf, tracked=feats.n_tracked,
                             stereo=feats.n_stereo, landmarks=active,
                             iterations=int(info.iterations), cost=cost, rows=slots.rows,
                             timings=timer.timings())

    def _reset(self, reason: Failure | ImuGap, t_ns: int, pred: BodyState | None,
               timer: StageTimer, feats: FrameFeatures) -> FrameEstimate:
        """Window -> no window: keep an IMU-propagated state and clear the window. After a
        failure the state is propagated from the newest one no failure test suspected (the
        frames since, which the tests counted, may already have pulled the window's velocity
        and bias off: shuffled tracks for 0.1 s before the outlier test fired left the coast
        0.5 m off 1.3 s later, 0.1 m from the trusted state), else ``pred``; across an IMU
        gap, the last good state held at constant velocity; outside the stream, none. The
        tracker keeps its corners (they start new landmarks): it may already be a frame ahead
        in the front-end thread."""
        state = pred
        trusted = self._trusted
        if isinstance(reason, Failure) and trusted is not None and trusted.t_ns < t_ns:
            iv = self.imu.slice(trusted.t_ns, t_ns)
            if iv.gap is None:
                state = trusted.propagate(iv.samples, self.noise, t_ns)[1]
        if state is None and self._last_good is not None and reason is not ImuGap.NO_IMU:
            state = self._last_good.hold(t_ns)
        self.resets += 1
        self._last_good = state
        self._trusted = None
        # re-initialise from the next frames' alignment (not at the propagated state)
        self._start = StartCheck(self.imu, self.T_BC0, self.config)
        self._new_window()
        return FrameEstimate(t_ns, state, "reset", reason.value, tracked=feats.n_tracked,
                             stereo=feats.n_stereo, timings=timer.timings())

    def _new_window(self) -> None:
        """An empty window, with its failure counts at zero."""
        self.window = SlidingWindow(self.config, self.noise, self.params)
        self._failures = FailureCounters()

    def _open(self, t_ns: int, state: BodyState, reason: str, feats: FrameFeatures,
              depths: tuple, timer: StageTimer) -> FrameEstimate:
        """Open the (empty) window at ``state``, this frame its first keyframe."""
        self.window.open(state, self._measurements(feats, depths))
        self.window.slots.kf_features, self.window.slots.kf_rotation = feats, state.rotation
        self._last_good = state
        timer.lap("solve")
        return FrameEstimate(t_ns, state, "initialized", reason, keyframe=True,
                             tracked=feats.n_tracked, stereo=feats.n_stereo,
                             landmarks=int(np.sum(self.window.slots.landmark_used)),
                             timings=timer.timings())

    def _open_window(self, t_ns: int, feats: FrameFeatures, timer: StageTimer
                     ) -> FrameEstimate:
        """The no-window phase: coast on the IMU from the last good state (none before the
        first start) until a frame has enough usable stereo matches, then open a window there."""
        cfg = self.config
        state = last = self._last_good
        if last is not None:
            iv = self.imu.slice(last.t_ns, t_ns)
            state = (last.hold(t_ns) if iv.gap is not None
                     else last.propagate(iv.samples, self.noise, t_ns)[1])
        depths = stereo_depths(feats, self.T_C0C1, cfg.min_stereo_depth, cfg.max_stereo_depth)
        if int(np.sum(depths[1])) < cfg.min_init_landmarks:
            if state is not None:
                self._last_good = state
            return FrameEstimate(t_ns, state, "waiting" if state is None else "coasting",
                                 tracked=feats.n_tracked, stereo=feats.n_stereo,
                                 timings=timer.timings())
        reason = "first"
        if state is not None and self._start is not None and cfg.init_frames >= 3:
            # after a reset: coast until the last frames align (a start while moving),
            # at most 3 * init_frames frames, then open at the IMU-propagated state
            self._start.add(t_ns, feats, depths)
            start = self._start.align(state)
            if start is None and not self._start.exhausted:
                self._last_good = state
                return FrameEstimate(t_ns, state, "coasting", "reinit",
                                     tracked=feats.n_tracked, stereo=feats.n_stereo,
                                     timings=timer.timings())
            state, reason = (start, "moving") if start is not None else (state, "propagated")
            self._start = None
        elif state is None:
            try:
                R0 = gravity_aligned_rotation(self.imu.accel_mean(t_ns, cfg.accel_init_s))
            except ValueError:
                return FrameEstimate(t_ns, None, "waiting", tracked=feats.n_tracked)
            state = BodyState.at_rest(t_ns, R0)
            if cfg.init_frames >= 3:  # check the levelled, at-rest start once frames align
                self._start = StartCheck(self.imu, self.T_BC0, cfg)
                self._start.add(t_ns, feats, depths)
        return self._open(t_ns, state, reason, feats, depths, timer)
