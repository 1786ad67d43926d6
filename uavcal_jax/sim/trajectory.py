"""Continuous-time, C2-smooth body trajectories for the simulator (numpy/scipy side).

A :class:`Trajectory` is a pair of quintic B-splines of time: the body (IMU) position in the
world frame, and an *unnormalised* quaternion ``p(t)`` (w, x, y, z) whose normalisation is
the body-to-world rotation. Both are four times continuously differentiable inside their
span, so position, velocity, acceleration, orientation and body angular velocity are all
continuous, and the synthetic IMU built from them (:mod:`uavcal_jax.sim.imu_synth`) is too.

The body angular velocity is exact for the spline::

    omega_B(t) = 2 Im(conj(p) ⊗ dp/dt) / |p|^2

(for ``p = s q`` with ``|q| = 1`` this is ``2 Im(conj(q) ⊗ dq/dt)``, whatever ``s(t)``).

Three ways to make one:

* :func:`fit_tum_trajectory` fits a recorded ground truth (a TUM file or a
  :class:`~uavcal_jax.data.sequence.GroundTruth`) with penalised least-squares quintic
  B-splines (knots every :attr:`FitConfig.knot_spacing` seconds, a tiny third-difference
  penalty that only matters where data are missing). Real motion-capture data are noisy, so
  the fit smooths: it passes frequencies up to ~5 Hz with unit gain and rolls off above
  ~8 Hz (with the default 0.05 s knots). Instantaneous position steps in the recording
  (EuRoC's Machine Hall ground truth has dozens) are removed first
  (:func:`remove_position_jumps`). The file's own clock is kept: ``t_start`` / ``t_end`` are
  absolute seconds of that clock.
* :func:`procedural_flight` draws a random quadrotor flight from a seed (hover, yaw turns,
  climbs and descents, straight legs, combined manoeuvres; 0-2 m/s) with the attitude a
  quadrotor needs for its acceleration: thrust (body z) along ``a + 9.81 e_z``, heading from a
  smooth yaw profile.
* :func:`straight_flight`: hover, accelerate, cruise along a line of a given length, stop,
  hover.

Times are float64 seconds. Every evaluation method takes ``t`` of any shape and returns
``t.shape + (3,)`` (or ``(4,)``, ``(3, 3)``). Asking for a time outside
``[t_start, t_end]`` (beyond 1 microsecond) raises ``ValueError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy.interpolate import BSpline, make_interp_spline
from scipy.ndimage import maximum_filter1d
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.errors import DataError

__all__ = [
    "GRAVITY",
    "FitConfig",
    "FlightConfig",
    "Trajectory",
    "TrajectoryState",
    "fit_tum_trajectory",
    "procedural_flight",
    "quat_conjugate",
    "quat_multiply",
    "quat_to_matrix",
    "remove_position_jumps",
    "sign_continuous",
    "straight_flight",
]

#: Standard gravity magnitude used throughout the simulator, m/s^2 (world gravity is -z).
GRAVITY = 9.81

#: Spline degree (quintic: position, velocity, acceleration and jerk are continuous).
DEGREE = 5

#: Tolerance for evaluating slightly outside ``[t_start, t_end]`` (seconds).
TIME_TOLERANCE = 1e-6


# --- quaternion helpers (numpy, w x y z) ------------------------------------------------------


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate of (..., 4) quaternions (w, x, y, z)."""
    return np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (w, x, y, z; normalised here)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    xyzw = Rotation.from_matrix(R).as_quat()
    return xyzw[..., [3, 0, 1, 2]]


def sign_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs of a (N, 4) quaternion sequence so consecutive ones have a positive dot."""
    q = np.array(q, dtype=np.float64, copy=True)
    if len(q) < 2:
        return q
    flips = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0.0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


# --- the trajectory ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TrajectoryState:
    """Everything the IMU synthesis and the ground-truth writer need at a set of times.

    Attributes: position, velocity, acceleration (N, 3) world; quaternion (N, 4) body-to-world
    (w, x, y, z, unit, sign-continuous along the spline); rotation (N, 3, 3) body-to-world;
    angular_velocity_body (N, 3) rad/s.
    """

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    quaternion: np.ndarray
    rotation: np.ndarray
    angular_velocity_body: np.ndarray


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A continuous-time body trajectory (see the module docstring).

    Attributes:
        t_start, t_end: the valid span, seconds (absolute seconds of the source's clock for
            fitted trajectories; ``FlightConfig.t0`` onwards for procedural ones).
        position_spline: ``BSpline`` of ``tau = t - t_ref`` -> (3,) world position, metres.
        quaternion_spline: ``BSpline`` of ``tau`` -> (4,) unnormalised quaternion (w, x, y, z).
        t_ref_ns: the spline's time origin in integer nanoseconds (``t_ref = t_ref_ns * 1e-9``).
        name: a label (file stem, ``"procedural-seed-3"`` ...).
    """

    t_start: float
    t_end: float
    position_spline: BSpline = field(repr=False)
    quaternion_spline: BSpline = field(repr=False)
    t_ref_ns: int = 0
    name: str = "trajectory"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.t_start) and np.isfinite(self.t_end)):
            raise ValueError("t_start and t_end must be finite")
        if self.t_end <= self.t_start:
            raise ValueError(f"empty trajectory span [{self.t_start}, {self.t_end}]")

    # -- time handling
    @property
    def t_ref(self) -> float:
        """The splines' time origin, float seconds."""
        return self.t_ref_ns * 1e-9

    @property
    def duration(self) -> float:
        return float(self.t_end - self.t_start)

    def _tau(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        lo, hi = np.min(t, initial=self.t_start), np.max(t, initial=self.t_end)
        if lo < self.t_start - TIME_TOLERANCE or hi > self.t_end + TIME_TOLERANCE:
            raise ValueError(
                f"{self.name}: time outside the trajectory span [{self.t_start:.6f}, "
                f"{self.t_end:.6f}] s (asked for {lo:.6f} .. {hi:.6f})"
            )
        return t - self.t_ref

    def _tau_ns(self, t_ns) -> np.ndarray:
        t_ns = np.asarray(t_ns, dtype=np.int64)
        tau = (t_ns - np.int64(self.t_ref_ns)).astype(np.float64) * 1e-9
        self._tau(tau + self.t_ref)  # range check only
        return tau

    def times(self, rate_hz: float) -> np.ndarray:
        """Regular sample times ``t_start + k / rate_hz`` inside the span (float seconds)."""
        n = int(math.floor(self.duration * rate_hz + 1e-9)) + 1
        return self.t_start + np.arange(n) / rate_hz

    # -- position
    def position(self, t) -> np.ndarray:
        """World position, metres, ``t.shape + (3,)``."""
        return self.position_spline(self._tau(t))

    def velocity(self, t) -> np.ndarray:
        """World velocity, m/s."""
        return self.position_spline(self._tau(t), nu=1)

    def acceleration(self, t) -> np.ndarray:
        """World acceleration (kinematic, gravity not included), m/s^2."""
        return self.position_spline(self._tau(t), nu=2)

    def jerk(self, t) -> np.ndarray:
        """World jerk, m/s^3."""
        return self.position_spline(self._tau(t), nu=3)

    # -- orientation
    def quaternion(self, t) -> np.ndarray:
        """Body-to-world unit quaternion (w, x, y, z), sign-continuous in time."""
        p = self.quaternion_spline(self._tau(t))
        return p / np.linalg.norm(p, axis=-1, keepdims=True)

    def rotation_matrix(self, t) -> np.ndarray:
        """Body-to-world rotation ``R_WB``, ``t.shape + (3, 3)``."""
        return quat_to_matrix(self.quaternion(t))

    def _omega_tau(self, tau: np.ndarray) -> np.ndarray:
        p = self.quaternion_spline(tau)
        dp = self.quaternion_spline(tau, nu=1)
        n2 = np.sum(p * p, axis=-1, keepdims=True)
        return 2.0 * quat_multiply(quat_conjugate(p), dp)[..., 1:] / n2

    def angular_velocity_body(self, t) -> np.ndarray:
        """Body angular velocity (what a perfect gyro reads), rad/s in the body (IMU) frame."""
        return self._omega_tau(self._tau(t))

    def angular_velocity_world(self, t) -> np.ndarray:
        """Angular velocity expressed in the world frame, rad/s."""
        tau = self._tau(t)
        R = quat_to_matrix(self.quaternion_spline(tau))
        return np.einsum("...ij,...j->...i", R, self._omega_tau(tau))

    # -- everything at once
    def _state_tau(self, tau: np.ndarray) -> TrajectoryState:
        p = self.quaternion_spline(tau)
        q = p / np.linalg.norm(p, axis=-1, keepdims=True)
        return TrajectoryState(
            position=self.position_spline(tau),
            velocity=self.position_spline(tau, nu=1),
            acceleration=self.position_spline(tau, nu=2),
            quaternion=q,
            rotation=quat_to_matrix(q),
            angular_velocity_body=self._omega_tau(tau),
        )

    def state(self, t) -> TrajectoryState:
        """Position, velocity, acceleration, orientation and body rate at ``t`` (seconds)."""
        return self._state_tau(self._tau(t))

    def state_ns(self, t_ns) -> TrajectoryState:
        """:meth:`state` at int64 nanosecond times, with the time origin subtracted exactly."""
        return self._state_tau(self._tau_ns(t_ns))

    # -- extent
    def bounds(self, dt: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box ``(lo (3,), hi (3,))`` containing the path (sampled every ``dt``)."""
        n = max(2, int(math.ceil(self.duration / dt)) + 1)
        pos = self.position(np.linspace(self.t_start, self.t_end, n))
        return pos.min(axis=0), pos.max(axis=0)

    # -- construction from samples
    @classmethod
    def from_samples(cls, t, position, quaternion, *, name: str = "samples",
                     t_ref_ns: int | None = None) -> Trajectory:
        """Quintic *interpolating* splines through exact samples (for analytic test motions).

        Args:
            t: (N,) strictly increasing seconds, N >= 6.
            position: (N, 3) world positions.
            quaternion: (N, 4) body-to-world (w, x, y, z); signs are made continuous.
            t_ref_ns: time origin (defaults to ``round(t[0] * 1e9)``).
        """
        t = np.asarray(t, dtype=np.float64)
        position = np.asarray(position, dtype=np.float64)
        quaternion = sign_continuous(np.asarray(quaternion, dtype=np.float64))
        if t.ndim != 1 or len(t) < DEGREE + 1 or np.any(np.diff(t) <= 0):
            raise ValueError("t must be (N,) strictly increasing with N >= 6")
        if position.shape != (len(t), 3) or quaternion.shape != (len(t), 4):
            raise ValueError(f"shapes disagree: t {t.shape}, position {position.shape}, "
                             f"quaternion {quaternion.shape}")
        if t_ref_ns is None:
            t_ref_ns = int(round(t[0] * 1e9))
        tau = t - t_ref_ns * 1e-9
        pos = make_interp_spline(tau, position, k=DEGREE)
        quat = make_interp_spline(tau, quaternion, k=DEGREE)
        return cls(float(t[0]), float(t[-1]), pos, quat, int(t_ref_ns), name)


# --- fitting recorded ground truth -------------------------------------------------------------


@dataclass(frozen=True)
class FitConfig:
    """How :func:`fit_tum_trajectory` smooths recorded poses.

    Attributes:
        knot_spacing: seconds between B-spline knots (0.05 s: flat response to ~5 Hz, cut-off
            near 10 Hz). It is widened to ``min_samples_per_knot`` sample periods for sparse
            data (e.g. 20 Hz ground truth gets 0.1 s).
        smoothing: weight of the third-difference penalty on the spline coefficients,
            relative to the data term per knot interval. The default 1e-4 barely changes the
            least-squares fit (gain 0.9 at 8 Hz); it keeps the solve well posed across gaps.
        edge_padding: seconds of extra data fitted on each side of a requested
            ``start``/``duration`` window (when the source has them), so the window's ends
            are free of spline edge effects.
        min_samples_per_knot: see ``knot_spacing``.
        jump_threshold: metres; position steps larger than this (and than
            ``jump_sigmas`` robust standard deviations of the data's noise) that the
            neighbouring samples do not share are removed before fitting, see
            :func:`remove_position_jumps`. ``None`` disables it.
        jump_sigmas, jump_max_jerk: see :func:`remove_position_jumps`.
    """

    knot_spacing: float = 0.05
    smoothing: float = 1e-4
    edge_padding: float = 1.0
    min_samples_per_knot: float = 2.0
    jump_threshold: float | None = 5e-4
    jump_sigmas: float = 8.0
    jump_max_jerk: float = 100.0


def _uniform_knots(tau0: float, tau1: float, spacing: float) -> np.ndarray:
    n_int = max(1, int(math.ceil((tau1 - tau0) / spacing - 1e-9)))
    h = (tau1 - tau0) / n_int
    inner = tau0 + h * np.arange(n_int + 1)
    inner[-1] = tau1
    return np.concatenate([tau0 + h * np.arange(-DEGREE, 0), inner,
                           tau1 + h * np.arange(1, DEGREE + 1)])


def _penalised_fit(tau: np.ndarray, values: np.ndarray, knots: np.ndarray,
                   smoothing: float, order: int = 3) -> np.ndarray:
    """Coefficients of the penalised least-squares quintic spline, several columns at once."""
    B = BSpline.design_matrix(tau, knots, DEGREE).tocsr()
    m = B.shape[1]
    D = sparse.eye(m, format="csr")
    for _ in range(order):
        D = D[1:] - D[:-1]
    per_knot = len(tau) / m
    A = (B.T @ B) / per_knot + smoothing * (D.T @ D)
    rhs = (B.T @ values) / per_knot
    lu = sparse_linalg.splu(sparse.csc_matrix(A))
    return lu.solve(np.asarray(rhs))


def remove_position_jumps(t: np.ndarray, position: np.ndarray, threshold: float = 5e-4,
                          sigmas: float = 8.0, max_jerk: float = 100.0,
                          max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Remove step discontinuities from recorded positions.

    Some ground truths have instantaneous position jumps that the body cannot have made
    (EuRoC's Machine Hall sequences: dozens of 1-130 mm steps between two 200 Hz samples,
    with the velocity continuous across them). Left in, each one is a huge acceleration
    spike in the synthetic IMU. A step at sample ``i`` is found from the residual of the
    velocity ``v_i = (p_{i+1} - p_i) / dt_i`` against the mean of its neighbours
    ``(v_{i-2} + v_{i+2}) / 2`` (zero to second order for smooth motion); the largest
    local residuals above ``max(threshold, sigmas * robust noise std, 2 max_jerk dt^3)`` (the
    last term is what real motion with that jerk leaves in the residual; it only matters for
    sparse data: 25 mm at 20 Hz with the default 100 m/s^3) are taken as jumps,
    every later sample is shifted back by the jump, and this repeats until none remain. The
    result is re-centred so the mean correction is zero. An isolated outlier sample shows
    up as two opposite jumps and is repaired the same way.

    Args:
        t: (N,) seconds, increasing.
        position: (N, 3).
        threshold: metres, the smallest step treated as a jump.
        sigmas: how many robust standard deviations of the residuals a jump must exceed.
        max_jerk: m/s^3, the largest jerk expected of the real motion.

    Returns:
        ``(corrected (N, 3), jumps (J,) indices i of the steps p_i -> p_{i+1})``.
    """
    p = np.array(position, dtype=np.float64, copy=True)
    t = np.asarray(t, dtype=np.float64)
    n = len(p)
    if n < 7:
        return p, np.zeros(0, dtype=np.int64)
    dt = np.diff(t)[:, None]
    found: list[np.ndarray] = []
    correction = np.zeros_like(p)
    limit = None
    for _ in range(max_iterations):
        v = np.diff(p, axis=0) / dt
        # residual of step s = 2 .. n-4 against its neighbours two steps away (an outlier
        # sample spoils two adjacent steps; these predictions skip both)
        resid = (v[2:-2] - 0.5 * (v[:-4] + v[4:])) * dt[2:-2]
        r = np.linalg.norm(resid, axis=1)
        if limit is None:
            mad = np.median(np.abs(resid - np.median(resid, axis=0)), axis=0)
            limit = max(threshold, sigmas * 1.4826 * float(np.linalg.norm(mad)),
                        2.0 * max_jerk * float(np.median(dt)) ** 3)
        local_max = maximum_filter1d(r, size=5, mode="constant", cval=0.0) <= r
        idx = np.flatnonzero(local_max & (r > limit))
        if idx.size == 0:
            break
        steps = np.zeros_like(p)
        steps[idx + 3] = resid[idx]  # resid[j] is the step from sample j+2 to j+3
        shift = np.cumsum(steps, axis=0)
        p -= shift
        correction += shift
        found.append(idx + 2)
    p += correction.mean(axis=0)
    jumps = np.unique(np.concatenate(found)) if found else np.zeros(0, dtype=np.int64)
    return p, jumps


def _load_ground_truth(source) -> tuple[GroundTruth, str]:
    if isinstance(source, GroundTruth):
        return source, "ground-truth"
    path = Path(source)
    from uavcal_jax.data.tum import read_tum

    return read_tum(path), path.stem


def fit_tum_trajectory(source: str | Path | GroundTruth, start: float | None = None,
                       duration: float | None = None,
                       config: FitConfig = FitConfig()) -> Trajectory:  # noqa: B008
    """Fit a smooth trajectory to recorded poses (TUM file or ``GroundTruth``).

    Position: one penalised least-squares quintic B-spline per axis (uniform knots). Rotation:
    the quaternions are made sign-continuous, each component is fitted the same way, and the
    result is normalised on evaluation (angular velocity from the unnormalised spline).

    Args:
        source: a TUM file (``t tx ty tz qx qy qz qw``, read with
            :func:`uavcal_jax.data.tum.read_tum`) or a ``GroundTruth`` (its position and
            quaternion; other fields are ignored).
        start: first time of the trajectory, absolute seconds of the source's clock
            (default: the first pose). Clipped to the data.
        duration: seconds (default: to the last pose). Clipped to the data.
        config: smoothing settings.

    Returns:
        A :class:`Trajectory` with ``t_start``/``t_end`` in the source's own clock.

    Raises:
        DataError: too few poses, or a window that does not overlap the data.
    """
    gt, name = _load_ground_truth(source)
    where = None if isinstance(source, GroundTruth) else Path(source)
    t_ns = np.asarray(gt.t_ns, dtype=np.int64)
    pos = np.asarray(gt.position, dtype=np.float64)
    quat = np.asarray(gt.quaternion, dtype=np.float64)
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"need at least {2 * (DEGREE + 1)} poses to fit a trajectory, "
                        f"got {len(t_ns)}", where)
    if np.any(np.diff(t_ns) <= 0):
        raise DataError("pose timestamps are not strictly increasing", where)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise DataError("non-finite poses", where)

    t_first, t_last = t_ns[0] * 1e-9, t_ns[-1] * 1e-9
    w0 = t_first if start is None else max(float(start), t_first)
    w1 = t_last if duration is None else min(w0 + float(duration), t_last)
    if start is not None and float(start) > t_last:
        raise DataError(f"start {start} s is after the last pose ({t_last:.6f} s)", where)
    if w1 - w0 <= 0:
        raise DataError(f"empty window [{w0}, {w1}] s", where)

    t = t_ns * 1e-9
    keep = (t >= w0 - config.edge_padding) & (t <= w1 + config.edge_padding)
    t_ns, pos, quat = t_ns[keep], pos[keep], quat[keep]
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"only {len(t_ns)} poses in the window [{w0}, {w1}] s", where)
    quat = sign_continuous(quat / np.linalg.norm(quat, axis=1, keepdims=True))

    t_ref_ns = int(t_ns[0])
    tau = (t_ns - t_ref_ns).astype(np.float64) * 1e-9
    if config.jump_threshold is not None:
        pos, _ = remove_position_jumps(tau, pos, config.jump_threshold, config.jump_sigmas,
                                       config.jump_max_jerk)
    period = float(np.median(np.diff(tau)))
    spacing = max(config.knot_spacing, config.min_samples_per_knot * period)
    knots = _uniform_knots(tau[0], tau[-1], spacing)
    coef = _penalised_fit(tau, np.concatenate([pos, quat], axis=1), knots, config.smoothing)
    pos_spline = BSpline(knots, coef[:, :3], DEGREE)
    quat_spline = BSpline(knots, coef[:, 3:], DEGREE)
    return Trajectory(float(w0), float(w1), pos_spline, quat_spline, t_ref_ns, name)


# --- procedural flights ------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightConfig:
    """Limits and ranges of procedural flights (SI units, radians).

    Attributes:
        t0: time of the first sample, seconds.
        start_position: where the flight starts (hovering), world metres.
        start_yaw: heading at the start (``None``: drawn from the seed).
        max_speed, max_accel: horizontal speed / acceleration limits.
        max_vertical_speed, max_vertical_accel: vertical limits.
        max_yaw_rate, max_yaw_accel: heading rate / acceleration limits.
        area_half_size: the flight stays within ``start +- area_half_size`` horizontally.
        altitude_range: allowed heights (world z).
        leg_length: range of straight-leg lengths.
        climb: range of height changes for climbs/descents.
        yaw_turn: range of yaw-turn magnitudes.
        hover_time: range of hover durations.
        min_speed_fraction: each manoeuvre's speed limit is drawn in
            ``[min_speed_fraction, 1] * max``.
        knot_spacing: B-spline knot spacing of the position / yaw splines, seconds.
        attitude_rate_hz: rate at which the quadrotor attitude is computed and interpolated.
    """

    t0: float = 0.0
    start_position: tuple[float, float, float] = (0.0, 0.0, 1.5)
    start_yaw: float | None = None
    max_speed: float = 2.0
    max_accel: float = 1.5
    max_vertical_speed: float = 0.8
    max_vertical_accel: float = 1.0
    max_yaw_rate: float = 1.0
    max_yaw_accel: float = 1.5
    area_half_size: tuple[float, float] = (5.0, 5.0)
    altitude_range: tuple[float, float] = (0.8, 3.0)
    leg_length: tuple[float, float] = (1.0, 6.0)
    climb: tuple[float, float] = (0.3, 1.2)
    yaw_turn: tuple[float, float] = (math.pi / 6, math.pi)
    hover_time: tuple[float, float] = (0.5, 2.5)
    min_speed_fraction: float = 0.3
    knot_spacing: float = 0.1
    attitude_rate_hz: float = 100.0


_RAMP_PEAK_ACCEL = 1.875  # max of d/ds (10 s^3 - 15 s^4 + 6 s^5)


def _ramp_integral(s: np.ndarray) -> np.ndarray:
    """Integral of the smootherstep ``10s^3 - 15s^4 + 6s^5`` from 0 to ``s`` (0.5 at s=1)."""
    s = np.clip(s, 0.0, 1.0)
    return s**4 * (2.5 - 3.0 * s + s * s)


@dataclass(frozen=True)
class _Segment:
    """Move by ``delta`` (x, y, z, yaw) in ``[t0, t0 + T]`` with a smooth trapezoid profile."""

    t0: float
    T: float
    T_ramp: float
    start: np.ndarray
    delta: np.ndarray

    def progress(self, t: np.ndarray) -> np.ndarray:
        """Normalised progress u(t) in [0, 1]; velocity is a smootherstep-ramped trapezoid."""
        if self.T_ramp <= 0.0:
            return np.ones_like(t)
        tau = np.clip(t - self.t0, 0.0, self.T)
        c = self.T - self.T_ramp  # distance / cruise speed, for unit distance
        r = self.T_ramp
        up = (r / c) * _ramp_integral(tau / r)
        mid = (0.5 * r + (tau - r)) / c
        down = 1.0 - (r / c) * _ramp_integral((self.T - tau) / r)
        return np.where(tau < r, up, np.where(tau <= self.T - r, mid, down))


def _profile_times(dists_limits: list[tuple[float, float, float]]) -> tuple[float, float]:
    """Total time T and ramp time of a shared profile meeting every (distance, v, a) limit.

    The unit profile has peak speed ``1 / c`` and peak acceleration ``1.875 / (c T_r)`` with
    ``c = T - T_r``; each axis scales them by its distance.
    """
    c = max((d / v for d, v, _ in dists_limits if d > 0), default=0.0)
    if c <= 0.0:
        return 0.0, 0.0
    r = max(_RAMP_PEAK_ACCEL * d / (a * c) for d, _, a in dists_limits if d > 0)
    if r > c:  # no cruise phase: c = T_r, both limits hold
        c = r = math.sqrt(max(_RAMP_PEAK_ACCEL * d / a for d, _, a in dists_limits if d > 0))
    return c + r, r


class _Plan:
    """Piecewise (x, y, z, yaw) plan made of hover and move segments."""

    def __init__(self, t0: float, start: np.ndarray):
        self.t = t0
        self.state = np.asarray(start, dtype=np.float64)
        self.segments: list[_Segment] = []

    def hover(self, T: float) -> None:
        self.segments.append(_Segment(self.t, T, 0.0, self.state.copy(), np.zeros(4)))
        self.t += T

    def move(self, delta: np.ndarray, v_h: float, a_h: float, v_z: float, a_z: float,
             v_yaw: float, a_yaw: float) -> None:
        delta = np.asarray(delta, dtype=np.float64)
        T, r = _profile_times([(float(np.hypot(delta[0], delta[1])), v_h, a_h),
                               (abs(float(delta[2])), v_z, a_z),
                               (abs(float(delta[3])), v_yaw, a_yaw)])
        if T <= 0.0:
            return
        self.segments.append(_Segment(self.t, T, r, self.state.copy(), delta))
        self.t += T
        self.state = self.state + delta

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.empty(t.shape + (4,))
        starts = np.array([s.t0 for s in self.segments])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.segments) - 1)
        for k in np.unique(idx):
            seg = self.segments[k]
            sel = idx == k
            out[sel] = seg.start + seg.progress(t[sel])[:, None] * seg.delta
        before = t < self.segments[0].t0
        out[before] = self.segments[0].start
        return out


def _flatness_trajectory(plan: _Plan, t0: float, duration: float, config: FlightConfig,
                         name: str) -> Trajectory:
    """Quintic splines through the plan, and the quadrotor attitude it implies."""
    margin = 1.0
    h = config.knot_spacing
    t_ref_ns = int(round(t0 * 1e9))
    knots = _uniform_knots(-margin, duration + margin, h)
    # Control points sampled at the Greville abscissae: the spline reproduces linear motion
    # exactly and smooths the plan by ~h.
    greville = np.array([knots[i + 1:i + DEGREE + 1].mean()
                         for i in range(len(knots) - DEGREE - 1)])
    ctrl = plan(t0 + greville)
    pos_spline = BSpline(knots, ctrl[:, :3], DEGREE)
    yaw_spline = BSpline(knots, ctrl[:, 3], DEGREE)

    n = int(math.ceil((duration + 2 * margin) * config.attitude_rate_hz)) + 1
    tau = np.linspace(-margin, duration + margin, n)
    thrust = pos_spline(tau, nu=2) + np.array([0.0, 0.0, GRAVITY])
    z_b = thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
    yaw = yaw_spline(tau)
    x_c = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
    y_b = np.cross(z_b, x_c)
    y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
    x_b = np.cross(y_b, z_b)
    R = np.stack([x_b, y_b, z_b], axis=2)
    quat = sign_continuous(_matrix_to_quat(R))
    quat_spline = make_interp_spline(tau, quat, k=DEGREE)
    return Trajectory(float(t0), float(t0 + duration), pos_spline, quat_spline, t_ref_ns, name)


def procedural_flight(seed: int, duration: float,
                      config: FlightConfig = FlightConfig()) -> Trajectory:  # noqa: B008
    """A random, smooth, quadrotor-like flight, deterministic for ``seed``.

    The flight starts hovering at ``config.start_position`` and chains manoeuvres drawn with
    ``numpy.random.default_rng(seed)``: hovers, yaw turns, climbs/descents, straight legs
    (some facing their direction of travel, some with a simultaneous climb or yaw change), each
    with a smootherstep-ramped trapezoidal speed profile within the configured speed and
    acceleration limits, inside ``area_half_size`` and ``altitude_range``. The position and yaw
    plans become quintic B-splines; the attitude is the quadrotor's: body z along the thrust
    ``a + 9.81 e_z``, body x in the vertical plane of the heading.

    Args:
        seed: random seed (an int).
        duration: seconds (> 0).
        config: limits and ranges.
    """
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    rng = np.random.default_rng(seed)
    c = config
    start = np.asarray(c.start_position, dtype=np.float64)
    yaw0 = float(rng.uniform(-math.pi, math.pi)) if c.start_yaw is None else float(c.start_yaw)
    plan = _Plan(c.t0, np.array([*start, yaw0]))
    plan.hover(float(rng.uniform(1.0, 2.0)))
    lo_xy, hi_xy = start[:2] - np.asarray(c.area_half_size), start[:2] + np.asarray(
        c.area_half_size)
    z_lo, z_hi = c.altitude_range

    def speeds(v: float) -> float:
        return v * float(rng.uniform(c.min_speed_fraction, 1.0))

    def limits() -> tuple[float, ...]:
        return (speeds(c.max_speed), c.max_accel, speeds(c.max_vertical_speed),
                c.max_vertical_accel, speeds(c.max_yaw_rate), c.max_yaw_accel)

    def climb_delta() -> float:
        z = plan.state[2]
        dz = float(rng.uniform(*c.climb)) * (1.0 if rng.random() < 0.5 else -1.0)
        if not z_lo <= z + dz <= z_hi:
            dz = -dz
        return float(np.clip(z + dz, z_lo, z_hi) - z)

    def leg_delta() -> np.ndarray:
        xy = plan.state[:2]
        for _ in range(8):
            heading = float(rng.uniform(-math.pi, math.pi))
            d = np.array([math.cos(heading), math.sin(heading)]) * float(
                rng.uniform(*c.leg_length))
            target = np.clip(xy + d, lo_xy, hi_xy)
            if np.linalg.norm(target - xy) >= 0.5 * c.leg_length[0]:
                return target - xy
        to_centre = start[:2] - xy
        return to_centre if np.linalg.norm(to_centre) > 1e-6 else np.array([c.leg_length[0], 0])

    def wrap_turn(target_yaw: float) -> float:
        return (target_yaw - plan.state[3] + math.pi) % (2 * math.pi) - math.pi

    while plan.t < c.t0 + duration + 2.0:
        kind = rng.choice(["hover", "yaw", "climb", "leg", "leg_facing", "combined"],
                          p=[0.12, 0.16, 0.14, 0.22, 0.18, 0.18])
        if kind == "hover":
            plan.hover(float(rng.uniform(*c.hover_time)))
        elif kind == "yaw":
            turn = float(rng.uniform(*c.yaw_turn)) * (1.0 if rng.random() < 0.5 else -1.0)
            plan.move([0, 0, 0, turn], *limits())
        elif kind == "climb":
            plan.move([0, 0, climb_delta(), 0], *limits())
        elif kind == "leg":
            d = leg_delta()
            plan.move([d[0], d[1], 0, 0], *limits())
        elif kind == "leg_facing":
            d = leg_delta()
            plan.move([0, 0, 0, wrap_turn(math.atan2(d[1], d[0]))], *limits())
            plan.move([d[0], d[1], 0, 0], *limits())
        else:  # a leg with a simultaneous climb and heading change
            d = leg_delta()
            dz = climb_delta() if rng.random() < 0.7 else 0.0
            dyaw = float(rng.uniform(-1.0, 1.0)) * c.yaw_turn[1] * 0.5
            plan.move([d[0], d[1], dz, dyaw], *limits())
        if rng.random() < 0.3:
            plan.hover(float(rng.uniform(0.2, 1.0)))
    return _flatness_trajectory(plan, c.t0, float(duration), c, f"procedural-seed-{seed}")


def straight_flight(length: float, speed: float = 1.0,
                    config: FlightConfig = FlightConfig(),  # noqa: B008
                    *, heading: float = 0.0, hover_time: float = 2.0) -> Trajectory:
    """Hover, fly ``length`` metres in a straight line at ``speed``, stop and hover.

    The body faces ``heading`` (radians from world x; the line runs along it), starting at
    ``config.start_position``. Speed ramps with ``config.max_accel`` (smootherstep ramps, so
    acceleration is continuous); the cruise speed is exactly ``speed`` when the line is long
    enough to reach it.
    """
    if length <= 0 or speed <= 0:
        raise ValueError("length and speed must be positive")
    start = np.asarray(config.start_position, dtype=np.float64)
    plan = _Plan(config.t0, np.array([*start, heading]))
    plan.hover(hover_time)
    d = length * np.array([math.cos(heading), math.sin(heading)])
    plan.move([d[0], d[1], 0.0, 0.0], speed, config.max_accel, 1.0, 1.0, 1.0, 1.0)
    plan.hover(hover_time + 3.0)
    duration = plan.t - config.t0 - 3.0
    return _flatness_trajectory(plan, config.t0, duration, config,
                                f"straight-{length:g}m-{speed:g}mps")
