"""Continuous-time, C2-smooth body trajectories for the simulator (numpy/scipy side).

A :class:`Trajectory` is a pair of quintic B-splines of time: the body (IMU) position in the
world frame, and an *unnormalised* quaternion ``p(t)`` (w, x, y, z) whose normalisation is
the body-to-world rotation. Both are four times continuously differentiable inside their
span, so position, velocity, acceleration, orientation and body angular velocity are all
continuous, and the synthetic IMU built from them (:mod:`uavcal_jax.sim.imu_synth`) is too.

The body angular velocity is exact for the spline::

    omega_B(t) = 2 Im(conj(p) ⊗ dp/dt) / |p|^2

(for ``p = s q`` with ``|q| = 1`` this is ``2 Im(conj(q) ⊗ dq/dt)``, whatever ``s(t)``).

Ways to make one: :meth:`Trajectory.from_samples` interpolates exact samples (analytic test
motions); :func:`uavcal_jax.sim.trajectory_fit.fit_tum_trajectory` fits a recorded ground
truth; :func:`uavcal_jax.sim.flights.procedural_flight` and
:func:`~uavcal_jax.sim.flights.straight_flight` plan quadrotor flights.

Times are float64 seconds. Every evaluation method takes ``t`` of any shape and returns
``t.shape + (3,)`` (or ``(4,)``, ``(3, 3)``). Asking for a time outside
``[t_start, t_end]`` (beyond 1 microsecond) raises ``ValueError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline
from scipy.spatial.transform import Rotation

__all__ = [
    "DEGREE",
    "Trajectory",
    "TrajectoryState",
    "sign_continuous",
    "uniform_knots",
]

#: Spline degree (quintic: position, velocity, acceleration and jerk are continuous).
DEGREE = 5

#: Tolerance for evaluating slightly outside ``[t_start, t_end]`` (seconds).
TIME_TOLERANCE = 1e-6


def _rotation_matrices(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (w, x, y, z; normalised by scipy).

    Flattened to (M, 4) because scipy's ``Rotation`` takes one batch axis only before 1.17."""
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)[:, [1, 2, 3, 0]]  # scipy's order is x, y, z, w
    return Rotation.from_quat(flat).as_matrix().reshape(q.shape[:-1] + (3, 3))


def _body_rate(p: np.ndarray, dp: np.ndarray) -> np.ndarray:
    """``2 Im(conj(p) ⊗ dp) / |p|^2`` for (..., 4) quaternions (w, x, y, z) ``p`` and their
    time derivatives ``dp``: the body angular velocity, rad/s (``dp`` is not a rotation, so
    this is the Hamilton product written out rather than a composition of rotations)."""
    w, v = p[..., :1], p[..., 1:]
    dw, dv = dp[..., :1], dp[..., 1:]
    im = w * dv - dw * v - np.cross(v, dv)
    return 2.0 * im / np.sum(p * p, axis=-1, keepdims=True)


def sign_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs of a (N, 4) quaternion sequence so consecutive ones have a positive dot."""
    q = np.array(q, dtype=np.float64, copy=True)
    if len(q) < 2:
        return q
    flips = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0.0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def uniform_knots(tau0: float, tau1: float, spacing: float) -> np.ndarray:
    """Knots of a degree-:data:`DEGREE` spline on ``[tau0, tau1]`` (seconds): the span cut into
    equal intervals of at most ``spacing``, plus ``DEGREE`` more beyond each end so that every
    point of the span has full B-spline support."""
    n_int = max(1, int(math.ceil((tau1 - tau0) / spacing - 1e-9)))
    h = (tau1 - tau0) / n_int
    inner = tau0 + h * np.arange(n_int + 1)
    inner[-1] = tau1
    return np.concatenate([tau0 + h * np.arange(-DEGREE, 0), inner,
                           tau1 + h * np.arange(1, DEGREE + 1)])


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

    # -- orientation
    def quaternion(self, t) -> np.ndarray:
        """Body-to-world unit quaternion (w, x, y, z), sign-continuous in time."""
        p = self.quaternion_spline(self._tau(t))
        return p / np.linalg.norm(p, axis=-1, keepdims=True)

    def rotation_matrix(self, t) -> np.ndarray:
        """Body-to-world rotation ``R_WB``, ``t.shape + (3, 3)``."""
        return _rotation_matrices(self.quaternion(t))

    def _omega_tau(self, tau: np.ndarray) -> np.ndarray:
        return _body_rate(self.quaternion_spline(tau), self.quaternion_spline(tau, nu=1))

    def angular_velocity_body(self, t) -> np.ndarray:
        """Body angular velocity (what a perfect gyro reads), rad/s in the body (IMU) frame."""
        return self._omega_tau(self._tau(t))

    def angular_velocity_world(self, t) -> np.ndarray:
        """Angular velocity expressed in the world frame, rad/s."""
        tau = self._tau(t)
        R = _rotation_matrices(self.quaternion_spline(tau))
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
            rotation=_rotation_matrices(q),
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
