"""The stereo VIO estimator: front end, IMU preintegration, window solve, marginalisation,
initialisation, failure detection and reset, frame by frame.

Per stereo frame (:meth:`StereoVio.process`):

1. the IMU samples since the previous frame are preintegrated at the newest keyframe's bias
   and predict the frame's state; their rotation seeds the optical flow;
2. the front end tracks the frame; the keyframe decision compares it with the last keyframe
   (gyro-compensated parallax, or too few tracks, or the last keyframe older than
   ``max_keyframe_interval_s``);
3. the frame enters the window's next slot at its IMU prediction, with an observation of
   every tracked corner whose landmark is alive and a new landmark for every other stereo
   match (inverse depth from the stereo triangulation);
4. the window is solved (:class:`~uavcal_jax.vio.solver.StructuredSolver`, warm start), then
   outliers are pruned (reprojection error over 3 px, depth out of range);
5. failure checks (non-finite state, bias beyond sane limits, the solved frame far from its
   IMU prediction, a cost blow-up, a long stretch without landmarks) reset the estimator:
   the IMU-propagated state is kept and the next frame with enough stereo matches starts a new
   window from it, so the trajectory continues;
6. the window slides as VINS-Mono: if the previous frame was not a keyframe it is dropped
   and its IMU interval merged (:func:`~uavcal_jax.vio.marginalize.drop_second_newest`),
   otherwise, once the window is full, the oldest keyframe is marginalised into the prior
   (:func:`~uavcal_jax.vio.marginalize.marginalize_oldest`).

A frame without features (black, blank, textureless) still enters the window with its IMU
interval only: the window then carries the state on the IMU and the prior, and tracking
resumes with new landmarks on the next textured frame.

Initialisation (:mod:`uavcal_jax.vio.initialize`): roll and pitch from the accelerometer
averaged over ``accel_init_s`` before the first frame (the body hovering or moving
uniformly), yaw and position zero, a gauge prior on the first keyframe; the gyro bias from
the visual rotations when the window first fills.

Output: one :class:`FrameEstimate` per frame (body pose ``T_WB`` of the IMU frame, flags,
timings); :func:`run_vio` runs a whole :class:`~uavcal_jax.data.sequence.Sequence`.

The back end runs under ``jax.enable_x64(True)`` (the estimator switches it on around its
calls).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import CameraCalibration, ImuCalibration, ImuData
from uavcal_jax.errors import DataError
from uavcal_jax.imu import NavState, interval_samples, predict
from uavcal_jax.vio.estimator_config import EstimatorConfig
from uavcal_jax.vio.frontend import FeatureTracker, FrameFeatures
from uavcal_jax.vio.initialize import (
    gauge_prior,
    gravity_aligned_rotation,
    gyro_bias_from_rotations,
    triangulate_stereo,
)
from uavcal_jax.vio.keyframes import body_to_camera_rotation, keyframe_decision
from uavcal_jax.vio.marginalize import (
    ImuSamples,
    drop_second_newest,
    marginalize_oldest,
    slide_imu_samples,
)
from uavcal_jax.vio.solver import structured_solve
from uavcal_jax.vio.window import CalibParams, Keyframes
from uavcal_jax.vio.window_ops import (
    empty_window,
    insert_frame,
    insert_solve_prune,
    preintegrate_padded,
    window_summary,
)

__all__ = ["STATUSES", "FrameEstimate", "StereoVio", "TrackedFrame"]

#: ``FrameEstimate.status`` values.
STATUSES = ("waiting", "initialized", "tracking", "coasting", "reset", "no_imu")
# IMU samples further apart than this many nominal periods are a gap the window cannot bridge
_IMU_GAP_PERIODS = 5.0
# padded row of one frame-to-frame interval (20 Hz frames, 200 Hz IMU: 11 samples)
_FRAME_SAMPLES = 32


@dataclasses.dataclass(frozen=True)
class FrameEstimate:
    """The estimate at one stereo frame.

    Attributes:
        t_ns: frame time, ns.
        has_pose: False before the first initialisation (nothing is known yet) and for frames
            outside the IMU stream.
        rotation: (3, 3) body-to-world rotation of the IMU (body) frame.
        position: (3,) m, world.  velocity: (3,) m/s, world.
        bias_gyro: (3,) rad/s.  bias_accel: (3,) m/s^2.
        status: one of :data:`STATUSES`: ``waiting`` (not initialised, no pose), ``initialized``
            (this frame started a window), ``tracking`` (solved with landmarks), ``coasting``
            (IMU propagation: no landmarks, or waiting to re-initialise after a reset),
            ``reset`` (a failure check fired at this frame; its pose is the IMU prediction),
            ``no_imu`` (outside the IMU stream).
        reason: why it reset (``nan``, ``bias``, ``jump``, ``cost``, ``blind``, ``imu_gap``), or
            why it is a keyframe, or ``""``.
        keyframe: the frame stayed in the window as a keyframe.
        tracked, stereo: the front end's corners and stereo matches.
        landmarks: landmarks observed in the window after the solve.
        iterations: solver iterations.  cost: the solved window cost.
        timings: milliseconds: ``frontend``, ``solve`` (insert, solve, prune), ``marginalize``
            (the slide), ``total``.
    """

    t_ns: int
    has_pose: bool
    rotation: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    status: str
    reason: str = ""
    keyframe: bool = False
    tracked: int = 0
    stereo: int = 0
    landmarks: int = 0
    iterations: int = 0
    cost: float = float("nan")
    timings: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class TrackedFrame:
    """The front end's output for one frame (:meth:`StereoVio.track`), the back end's input.

    Attributes:
        t_ns: frame time, ns.  features: the tracker's :class:`FrameFeatures`.
        frontend_ms: milliseconds the stage took.
    """

    t_ns: int
    features: FrameFeatures
    frontend_ms: float


@dataclasses.dataclass
class _Nav:
    """Host copy of a navigation state with its biases (float64 NumPy)."""

    t_ns: int
    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    bg: np.ndarray
    ba: np.ndarray


def _keyframe(nav: _Nav) -> Keyframes:
    # NumPy leaves: jitted callees convert them in one go (an eager jnp.asarray per leaf
    # costs a dispatch each)
    return Keyframes(nav.R, nav.p, nav.v, nav.bg, nav.ba)


def _slot_nav(state, slot: int, t_ns: int) -> _Nav:
    # one transfer of the (small) keyframe arrays, indexed on the host: eager device
    # indexing costs a dispatch per leaf
    f = jax.device_get(state.frames)
    return _Nav(t_ns, *(np.array(x[slot]) for x in (f.rotation, f.position, f.velocity,
                                                     f.bias_gyro, f.bias_accel)))


def _hold(nav: _Nav, t_ns: int) -> _Nav:
    """``nav`` carried to ``t_ns`` at constant velocity: across an interval the IMU does not
    cover (a gap), the one prediction left."""
    dt = (t_ns - nav.t_ns) * 1e-9
    return _Nav(t_ns, nav.R, nav.p + nav.v * dt, nav.v, nav.bg, nav.ba)


_predict = jax.jit(predict)


class StereoVio:
    """Stateful stereo-inertial odometry over one stream of frames.

    Args:
        left, right: the stereo cameras' calibrations (``T_BS``: camera to body (IMU)).
        imu_calibration: rate, IMU-to-body ``T_BS`` (must be the identity: the body frame is
            the IMU's) and noise model.
        imu: the whole IMU stream (samples already corrected for any known offset).
        config: :class:`~uavcal_jax.vio.estimator_config.EstimatorConfig`.
    """

    def __init__(self, left: CameraCalibration, right: CameraCalibration,
                 imu_calibration: ImuCalibration, imu: ImuData,
                 config: EstimatorConfig | None = None):
        self.config = cfg = config if config is not None else EstimatorConfig()
        if not np.allclose(imu_calibration.T_BS, np.eye(4), atol=1e-9):
            raise DataError("the IMU's T_BS is not the identity: the estimator's body frame is "
                            "the IMU frame; express the cameras' T_BS relative to the IMU")
        self.tracker = FeatureTracker(left, right, cfg.frontend)
        self.noise = imu_calibration.noise
        self.imu_period = 1.0 / imu_calibration.rate_hz
        self.imu = imu
        self.T_C0C1 = np.linalg.inv(np.asarray(left.T_BS, np.float64)) @ np.asarray(
            right.T_BS, np.float64)
        self.R_BC0 = np.asarray(left.T_BS, np.float64)[:3, :3]
        T = np.stack([np.asarray(left.T_BS, np.float64), np.asarray(right.T_BS, np.float64)])
        with jax.enable_x64(True):
            self.params = CalibParams(jnp.zeros(6), jnp.asarray(T[:, :3, :3]),
                                      jnp.asarray(T[:, :3, 3]))
        self.resets = 0
        self._last_good: _Nav | None = None
        # the front end's own view: its previous frame; and the newest gyro bias the back end
        # published, which seeds the flow (read through flow_bias(), a snapshot, never by a
        # front end running concurrently with update())
        self._fe_t_ns: int | None = None
        self._published_bias_gyro = np.zeros(3)
        self._depth_for: FrameFeatures | None = None
        self._clear_window()

    # --- window bookkeeping ---------------------------------------------------------------

    def _clear_window(self) -> None:
        cfg = self.config
        with jax.enable_x64(True):
            self.state, self.problem, self.samples = empty_window(
                cfg.keyframes, cfg.landmarks, cfg.observations, cfg.imu_samples, self.noise,
                cfg.cost)
        self.n = -1  # newest used slot
        self.slot_t: list[int] = []
        self.slot_kf: list[bool] = []
        self.id_to_landmark: dict[int, int] = {}
        self.lm_used = np.zeros(cfg.landmarks, bool)
        self.obs_used = np.zeros(cfg.observations, bool)
        self.kf_features: FrameFeatures | None = None
        self.kf_R: np.ndarray | None = None
        self.blind = 0
        self.filled_once = False

    def _mirror(self) -> int:
        """Read the device's landmark and observation masks back; forget dead landmarks.
        Returns the number of active landmarks."""
        return self._apply_summary(jax.device_get(window_summary(self.problem)))

    def _apply_summary(self, s: dict) -> int:
        """:meth:`_mirror` from a :func:`window_summary` already on the host."""
        self.lm_used = np.array(s["landmark_mask"])
        self.obs_used = np.array(s["observation_mask"])
        self.id_to_landmark = {i: l for i, l in self.id_to_landmark.items() if self.lm_used[l]}
        self._rows = int(s["rows"])
        return int(s["active_landmarks"])

    # --- IMU ------------------------------------------------------------------------------

    def _interval(self, t0_ns: int, t1_ns: int):
        """Samples of ``[t0, t1]`` padded to a short row (or to the window's ``imu_samples``
        when longer), or the reason string ``"no_imu"`` / ``"imu_gap"``."""
        iv = self._raw_interval(t0_ns, t1_ns)
        if iv is None:
            return "no_imu"
        if iv.dt.max() > _IMU_GAP_PERIODS * self.imu_period:
            return "imu_gap"
        n = len(iv.dt)
        if n > self.config.imu_samples:
            return "imu_gap"
        # the per-frame preintegration scans a short row; a long interval (dropped frames)
        # takes the window's full row
        S = _FRAME_SAMPLES if n <= _FRAME_SAMPLES else self.config.imu_samples
        dt = np.full(S, self.imu_period)
        gyro = np.zeros((S, 3))
        accel = np.zeros((S, 3))
        mask = np.zeros(S, bool)
        dt[:n], gyro[:n], accel[:n], mask[:n] = iv.dt, iv.gyro, iv.accel, True
        return ImuSamples(dt, gyro, accel, mask)

    def _raw_interval(self, t0_ns: int, t1_ns: int):
        """:func:`~uavcal_jax.imu.interval_samples` of ``[t0, t1]`` on the few samples around it
        (validating the whole stream every frame would cost more than integrating), or
        ``None`` when the interval is not inside the stream."""
        t = self.imu.t_ns
        lo = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(t, t1_ns, side="left")) + 1, len(t))
        try:
            return interval_samples(t[lo:hi], self.imu.gyro[lo:hi], self.imu.accel[lo:hi],
                                    t0_ns, t1_ns)
        except DataError:
            return None

    def _full_row(self, row: ImuSamples) -> ImuSamples:
        """``row`` padded to the window's ``imu_samples`` (what merging intervals needs)."""
        S = self.config.imu_samples
        n = row.dt.shape[0]
        if n == S:
            return row
        return ImuSamples(np.pad(row.dt, (0, S - n), constant_values=self.imu_period),
                          np.pad(row.gyro, ((0, S - n), (0, 0))),
                          np.pad(row.accel, ((0, S - n), (0, 0))),
                          np.pad(row.mask, (0, S - n)))

    def _propagate(self, nav: _Nav, row: ImuSamples, t_ns: int):
        """``(pim, nav at t_ns)`` by preintegration at ``nav``'s biases."""
        pim = preintegrate_padded(row.dt, row.gyro, row.accel, row.mask, nav.bg, nav.ba,
                                  self.noise, row.dt.shape[0])
        out = _predict(NavState(nav.R, nav.p, nav.v), pim)
        R, p, v = (np.asarray(x) for x in (out.rotation, out.position, out.velocity))
        return pim, _Nav(t_ns, R, p, v, nav.bg.copy(), nav.ba.copy())

    def _accel_mean(self, t_ns: int) -> np.ndarray:
        t = self.imu.t_ns
        sel = (t <= t_ns) & (t >= t_ns - int(self.config.accel_init_s * 1e9))
        if sel.sum() < 3:
            sel = np.argsort(np.abs(t - t_ns))[:max(3, int(self.config.accel_init_s
                                                           / self.imu_period))]
        return np.mean(self.imu.accel[sel], axis=0)

    # --- landmarks and observations -------------------------------------------------------

    def _stereo_depths(self, feats: FrameFeatures) -> tuple[np.ndarray, np.ndarray]:
        """``(depth (K,) m, usable (K,) bool)`` of each corner's stereo triangulation (NaN
        without a stereo match), memoised per frame: initialisation counts them and the
        measurements use them."""
        if self._depth_for is not feats:
            depth = np.full(len(feats.mask), np.nan)
            st = feats.stereo_mask
            if st.any():
                depth[st] = triangulate_stereo(feats.xy[st], feats.xy_right[st], self.T_C0C1)
            cfg = self.config
            self._depth_for = feats
            self._depth = (depth, (depth >= cfg.min_stereo_depth)
                           & (depth <= cfg.max_stereo_depth))
        return self._depth

    def _measurements(self, feats: FrameFeatures):
        """Padded updates for :func:`insert_frame`: observations of the corners whose landmark
        is alive, a new landmark for every other stereo match with a sane depth."""
        cfg = self.config
        K = cfg.frontend.max_features
        L, M = cfg.landmarks, cfg.observations
        lm_slot = np.full(K, L, np.int32)
        lm_bearing = np.zeros((K, 2))
        lm_inv = np.ones(K)
        o_slot = np.full(2 * K, M, np.int32)
        o_lm = np.zeros(2 * K, np.int32)
        o_cam = np.zeros(2 * K, np.int32)
        o_xy = np.zeros((2 * K, 2))
        valid = np.flatnonzero(feats.mask)
        stereo = feats.stereo_mask
        depth, good_depth = self._stereo_depths(feats)
        free_lm = iter(np.flatnonzero(~self.lm_used))
        free_obs = np.flatnonzero(~self.obs_used)
        n_lm = n_obs = 0
        entries = []  # (landmark slot, camera, xy)
        for i in valid:
            fid = int(feats.ids[i])
            lid = self.id_to_landmark.get(fid)
            if lid is None:
                if not (stereo[i] and good_depth[i]):
                    continue
                lid = next(free_lm, None)
                if lid is None:
                    continue
                self.id_to_landmark[fid] = lid
                self.lm_used[lid] = True
                lm_slot[n_lm], lm_bearing[n_lm], lm_inv[n_lm] = lid, feats.xy[i], 1.0 / depth[i]
                n_lm += 1
                entries.append((lid, 1, feats.xy_right[i]))
                continue
            entries.append((lid, 0, feats.xy[i]))
            if stereo[i]:
                entries.append((lid, 1, feats.xy_right[i]))
        for lid, cam, xy in entries[:len(free_obs)]:
            o_slot[n_obs], o_lm[n_obs], o_cam[n_obs], o_xy[n_obs] = free_obs[n_obs], lid, cam, xy
            n_obs += 1
        self.obs_used[o_slot[:n_obs]] = True
        return lm_slot, lm_bearing, lm_inv, o_slot, o_lm, o_cam, o_xy

    # --- the frame ------------------------------------------------------------------------

    def process(self, t_ns: int, img_left: np.ndarray | None, img_right: np.ndarray | None
                ) -> FrameEstimate:
        """Process one stereo frame (either image may be ``None``: a dropped frame):
        :meth:`track` (seeded at the newest published gyro bias) then :meth:`update`."""
        return self.update(self.track(t_ns, img_left, img_right, self.flow_bias()))

    def flow_bias(self) -> np.ndarray:
        """(3,) rad/s, a copy of the newest gyro bias :meth:`update` published (zero before
        the first pose): what a caller hands :meth:`track` to seed the flow."""
        return self._published_bias_gyro.copy()

    def track(self, t_ns: int, img_left: np.ndarray | None, img_right: np.ndarray | None,
              bias_gyro: np.ndarray) -> TrackedFrame:
        """The front end of one frame: the gyro rotation since the previous frame, corrected
        by ``bias_gyro`` (3,) rad/s, seeds the optical flow. Touches only the tracker and the
        front end's own state, so it may run in another thread than :meth:`update` (one
        frame ahead of it: OpenCV and XLA release the GIL). The bias is an argument, not read
        here, so that which estimate seeds the flow is decided by the caller (a snapshot
        taken when the task is handed out, :meth:`flow_bias`) and not by thread timing."""
        t_ns = int(t_ns)
        t0 = time.perf_counter()
        bias_gyro = np.asarray(bias_gyro, np.float64).reshape(3)
        R_gyro = None
        if self._fe_t_ns is not None and t_ns > self._fe_t_ns:
            iv = self._raw_interval(self._fe_t_ns, t_ns)
            if iv is not None:
                R_gyro = np.eye(3)
                for dt, w in zip(iv.dt, iv.gyro - bias_gyro, strict=True):
                    R_gyro = R_gyro @ Rotation.from_rotvec(w * dt).as_matrix()
        self._fe_t_ns = t_ns
        feats = self.tracker.track(t_ns * 1e-9, img_left, img_right, R_gyro)
        return TrackedFrame(t_ns, feats, 1e3 * (time.perf_counter() - t0))

    def update(self, frame: TrackedFrame) -> FrameEstimate:
        """The back end of one frame (:meth:`track`'s output, in time order)."""
        with jax.enable_x64(True):
            est = self._update(frame)
        if est.has_pose:
            self._published_bias_gyro = np.array(est.bias_gyro, np.float64)
        return est

    def _estimate(self, nav: _Nav | None, status: str, t_ns: int, **kw) -> FrameEstimate:
        if nav is None:
            nan3 = np.full(3, np.nan)
            return FrameEstimate(t_ns, False, np.full((3, 3), np.nan), nan3, nan3, nan3, nan3,
                                 status, **kw)
        return FrameEstimate(t_ns, True, nav.R, nav.p, nav.v, nav.bg, nav.ba, status, **kw)

    def _update(self, frame: TrackedFrame) -> FrameEstimate:
        clock = time.perf_counter
        t_start = clock()
        t_ns, feats = frame.t_ns, frame.features
        fe_ms = frame.frontend_ms
        if self.n < 0:
            return self._initialize(t_ns, feats, fe_ms, t_start)

        prev = _slot_nav(self.state, self.n, self.slot_t[self.n])
        row = self._interval(prev.t_ns, t_ns)
        if isinstance(row, str):
            return self._fail(row, t_ns, None, t_start, {"frontend": fe_ms}, feats)
        pim, pred = self._propagate(prev, row, t_ns)
        row = self._full_row(row)
        R_kf_cur = body_to_camera_rotation(self.kf_R.T @ pred.R, self.R_BC0)
        dec = keyframe_decision(self.kf_features.ids, self.kf_features.xy, feats.ids, feats.xy,
                                feats.mask, R_kf_cur, self.config.keyframe)
        is_kf, reason = dec.is_keyframe, dec.reason
        if not is_kf and (t_ns - self.slot_t[self._last_kf_slot()]) * 1e-9 \
                > self.config.max_keyframe_interval_s:
            is_kf, reason = True, "interval"

        s = self.n + 1
        upd = self._measurements(feats)
        self.state, self.problem, self.samples, info, summary, newest = insert_solve_prune(
            self.state, self.problem, self.samples, s, _keyframe(pred), pim, row, upd,
            self.params, self.config.solver, self.config.min_stereo_depth * 0.5)
        info, summary, newest = jax.device_get((info, summary, newest))
        active = self._apply_summary(summary)
        self.n = s
        self.slot_t.append(t_ns)
        self.slot_kf.append(is_kf)
        est = _Nav(t_ns, *(np.array(x) for x in (newest.rotation, newest.position,
                                                 newest.velocity, newest.bias_gyro,
                                                 newest.bias_accel)))
        t_solve = clock()
        timings = {"frontend": fe_ms, "solve": 1e3 * (t_solve - t_start)}

        self.blind = self.blind + 1 if active < self.config.limits.min_landmarks else 0
        failure = self._failure(est, pred, float(info.cost_final), active)
        if failure:
            return self._fail(failure, t_ns, pred, t_start, timings, feats=feats)

        if is_kf:
            self.kf_features, self.kf_R = feats, est.R
        self._slide()
        if not self.filled_once and self.n >= self.config.keyframes - 2:
            self._refine_gyro_bias()
        t_end = clock()
        timings |= {"marginalize": 1e3 * (t_end - t_solve),
                    "total": fe_ms + 1e3 * (t_end - t_start)}
        self._last_good = est
        status = "tracking" if active >= self.config.limits.min_landmarks else "coasting"
        return self._estimate(est, status, t_ns, reason=reason, keyframe=is_kf,
                              tracked=feats.n_tracked, stereo=feats.n_stereo, landmarks=active,
                              iterations=int(info.iterations), cost=float(info.cost_final),
                              timings=timings)

    def _last_kf_slot(self) -> int:
        return max(i for i, kf in enumerate(self.slot_kf) if kf)

    def _failure(self, est: _Nav, pred: _Nav, cost: float, active: int) -> str:
        lim = self.config.limits
        values = np.concatenate([est.R.ravel(), est.p, est.v, est.bg, est.ba])
        if not (np.all(np.isfinite(values)) and np.isfinite(cost)):
            return "nan"
        if (np.linalg.norm(est.bg) > lim.max_bias_gyro
                or np.linalg.norm(est.ba) > lim.max_bias_accel):
            return "bias"
        cos = np.clip(0.5 * (np.trace(pred.R.T @ est.R) - 1.0), -1.0, 1.0)
        if (np.linalg.norm(est.p - pred.p) > lim.max_translation_jump
                or np.degrees(np.arccos(cos)) > lim.max_rotation_jump_deg):
            return "jump"
        if cost > lim.max_cost_per_residual * max(self._rows, 1):
            return "cost"
        if self.blind > lim.max_blind_frames:
            return "blind"
        return ""

    def _fail(self, reason: str, t_ns: int, pred: _Nav | None, t_start: float, timings: dict,
              feats: FrameFeatures | None = None) -> FrameEstimate:
        """Reset: keep the IMU-propagated state and clear the window."""
        nav = pred
        if nav is None and self._last_good is not None and reason != "no_imu":
            nav = _hold(self._last_good, t_ns)
        if reason == "no_imu" and self.n < 0:
            return self._estimate(None, "no_imu", t_ns)
        self.resets += 1
        self._last_good = nav
        # the tracker keeps its corners (they start new landmarks): it may already be a frame
        # ahead in the front-end thread
        self._clear_window()
        timings = {"frontend": 0.0, "solve": 0.0, "marginalize": 0.0, **timings}
        timings["total"] = timings["frontend"] + 1e3 * (time.perf_counter() - t_start)
        return self._estimate(nav, "reset", t_ns, reason=reason,
                              tracked=0 if feats is None else feats.n_tracked,
                              stereo=0 if feats is None else feats.n_stereo, timings=timings)

    def _slide(self) -> None:
        cfg = self.config
        s = self.n
        if s >= 1 and not self.slot_kf[s - 1]:
            self.state, self.problem, self.samples = drop_second_newest(
                self.state, self.problem, self.samples, self.noise, self.params,
                cfg.marginalize)
            del self.slot_t[s - 1], self.slot_kf[s - 1]
            self.n = s - 1
        elif s == cfg.keyframes - 1:
            self.state, self.problem = marginalize_oldest(self.state, self.problem, self.params,
                                                          cfg.marginalize)
            self.samples = slide_imu_samples(self.samples)
            del self.slot_t[0], self.slot_kf[0]
            self.n = s - 1
            self.filled_once = True
        else:
            return
        self._mirror()

    def _refine_gyro_bias(self) -> None:
        """When the window first fills: the gyro bias from the keyframes' (visual) rotations,
        applied to every keyframe, then a re-solve (VINS-Mono's initial gyro-bias step)."""
        n = self.n
        if n < 2:
            return
        f = jax.device_get(self.state.frames)
        pim = jax.device_get(self.problem.imu.pim)
        use = np.asarray(self.problem.imu.mask)[:n]
        if not use.all():
            return
        d = gyro_bias_from_rotations(f.rotation[:n + 1], pim.delta_R[:n], pim.d_R_d_bg[:n])
        if not np.all(np.isfinite(d)) or np.linalg.norm(d) > self.config.limits.max_bias_gyro:
            return
        frames = dataclasses.replace(self.state.frames,
                                     bias_gyro=self.state.frames.bias_gyro + jnp.asarray(d))
        self.state = dataclasses.replace(self.state, frames=frames)
        self.state, _ = structured_solve(self.state, self.problem, self.params,
                                         self.config.solver)
        self.filled_once = True

    def _initialize(self, t_ns: int, feats: FrameFeatures, fe_ms: float, t_start: float
                    ) -> FrameEstimate:
        """Start a window at this frame when it has enough stereo landmarks."""
        cfg = self.config
        nav = None
        if self._last_good is not None:
            row = self._interval(self._last_good.t_ns, t_ns)
            if isinstance(row, str):
                nav = _hold(self._last_good, t_ns)
            else:
                _, nav = self._propagate(self._last_good, row, t_ns)
        n_good = int(np.sum(self._stereo_depths(feats)[1]))
        if n_good < cfg.min_init_landmarks:
            if nav is not None:
                self._last_good = nav
            status = "coasting" if nav is not None else "waiting"
            return self._estimate(nav, status, t_ns, tracked=feats.n_tracked,
                                  stereo=feats.n_stereo,
                                  timings={"frontend": fe_ms, "solve": 0.0, "marginalize": 0.0,
                                           "total": fe_ms + 1e3 * (time.perf_counter()
                                                                   - t_start)})
        first = nav is None
        if first:
            try:
                R0 = gravity_aligned_rotation(self._accel_mean(t_ns))
            except ValueError:
                return self._estimate(None, "waiting", t_ns, tracked=feats.n_tracked)
            nav = _Nav(t_ns, R0, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
        upd = self._measurements(feats)
        N = cfg.keyframes
        frames = jax.tree_util.tree_map(
            lambda a, x: a.at[0].set(x), self.state.frames, _keyframe(nav))
        prior = gauge_prior(frames, N, cfg.prior)
        self.problem = dataclasses.replace(self.problem, prior=prior)
        self.state = dataclasses.replace(self.state, frames=frames)
        dummy = jax.tree_util.tree_map(lambda x: x[0], self.problem.imu.pim)  # unused: slot 0
        row0 = jax.tree_util.tree_map(lambda x: x[0], self.samples)
        self.state, self.problem, self.samples = insert_frame(
            self.state, self.problem, self.samples, 0, _keyframe(nav), dummy, row0, *upd)
        self._mirror()
        self.n = 0
        self.slot_t = [t_ns]
        self.slot_kf = [True]
        self.kf_features, self.kf_R = feats, nav.R
        self._last_good = nav
        t_end = time.perf_counter()
        return self._estimate(nav, "initialized", t_ns, reason="first", keyframe=True,
                              tracked=feats.n_tracked, stereo=feats.n_stereo,
                              landmarks=int(np.sum(self.lm_used)),
                              timings={"frontend": fe_ms, "solve": 1e3 * (t_end - t_start),
                                       "marginalize": 0.0,
                                       "total": fe_ms + 1e3 * (t_end - t_start)})
