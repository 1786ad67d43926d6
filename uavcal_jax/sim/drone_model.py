"""A kinematic quadrotor that flies position and yaw set-points, and the IMU it carries.

Frames. ``W`` world (z up, gravity ``(0, 0, -9.81)``); ``Q`` the quadrotor (x forward, y left,
z up: the thrust axis). The state at IMU sample ``k`` (period ``dt = 1 / rate_hz``) is the
position ``p`` (3,) m, velocity ``v`` (3,) m/s, acceleration ``a`` (3,) m/s^2 (world) and yaw
(radians, heading of Q's x axis about world z, unwrapped).

Control (a cascaded position loop, as PX4's multicopter position controller, in its simplest
form)::

    v_des = clip_norm(v_ff + k_p (p_sp - p), max_speed)
    a_cmd = clip_norm(k_v (v_des - v - tau a), max_accel)     # the lag's lead compensation
    a    <- a + (a_cmd - a) dt / tau                          # thrust/attitude lag
    yaw  <- yaw + clip(k_yaw wrap(yaw_sp - yaw), +-max_yaw_rate) dt

``a`` is a convex mix of commands inside the ``max_accel`` ball, so ``|a| <= max_accel``; the
lag makes it continuous, hence the attitude too (no step in roll or pitch, bounded body
rates). Position and velocity integrate with ``a`` held over the step (exact for a
piecewise-constant acceleration)::

    p_{k+1} = p_k + v_k dt + a_k dt^2 / 2,   v_{k+1} = v_k + a_k dt

Attitude (quadrotor-style, Mellinger and Kumar 2011): the thrust axis is along ``a - g``;
``R_WQ`` has that z axis and the x axis nearest the yaw heading (:func:`attitude`).

IMU (in Q), consistent with the same zero-order hold the preintegration uses (sample ``k``
held over ``[t_k, t_{k+1})``, :func:`uavcal_jax.imu.interval_samples`)::

    gyro_k  = Log(R_k^T R_{k+1}) / dt          (constant body rate that reaches R_{k+1})
    accel_k = R_k^T (a_k - g)                  (specific force)

so integrating them from the true initial state gives back the poses (rotation exactly;
position up to the rotation within one step). Sample ``k`` needs state ``k + 1``, so a flight
of ``n`` steps yields ``n`` samples (``0 .. n - 1``). Pure NumPy, float64.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc_rig import EUROC_IMU_RATE_HZ
from uavcal_jax.geometry.frames import GRAVITY_W

__all__ = ["DroneConfig", "DroneFlight", "DroneState", "attitude", "fly", "hover_state",
           "imu_samples", "wrap"]


@dataclasses.dataclass(frozen=True)
class DroneConfig:
    """Limits and gains of the kinematic drone.

    Attributes:
        max_speed: speed limit, m/s.
        max_accel: acceleration limit (world, gravity excluded), m/s^2 (tilt up to about
            ``atan(max_accel / 9.81)``).
        max_yaw_rate: yaw rate limit, rad/s.
        position_gain: ``k_p``, 1/s.  velocity_gain: ``k_v``, 1/s.  yaw_gain: ``k_yaw``, 1/s.
        accel_tau: time constant of the acceleration (attitude and thrust) lag, seconds.
        rate_hz: integration (and IMU) rate, Hz.
    """

    max_speed: float = 3.0
    max_accel: float = 3.0
    max_yaw_rate: float = 1.5
    position_gain: float = 1.5
    velocity_gain: float = 3.0
    yaw_gain: float = 3.0
    accel_tau: float = 0.1
    rate_hz: float = EUROC_IMU_RATE_HZ

    def __post_init__(self):
        for name in ("max_speed", "max_accel", "max_yaw_rate", "position_gain",
                     "velocity_gain", "yaw_gain", "accel_tau", "rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"drone {name} must be > 0, got {getattr(self, name)}")

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz


@dataclasses.dataclass(frozen=True)
class DroneState:
    """The drone at one instant: ``p``, ``v``, ``a`` (3,) world m, m/s, m/s^2; ``yaw`` rad."""

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: float


@dataclasses.dataclass(frozen=True)
class DroneFlight:
    """``n`` steps of flight: the states at samples ``0 .. n`` (the first is the start).

    Attributes:
        p, v, a: (n + 1, 3) world position, velocity, acceleration.
        yaw: (n + 1,) radians (unwrapped).
        R_WQ: (n + 1, 3, 3) quadrotor-to-world rotations.
    """

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: np.ndarray
    R_WQ: np.ndarray

    def state(self, k: int = -1) -> DroneState:
        return DroneState(self.p[k].copy(), self.v[k].copy(), self.a[k].copy(),
                          float(self.yaw[k]))


def wrap(angle):
    """Angles wrapped to ``[-pi, pi)``."""
    return np.mod(np.asarray(angle) + np.pi, 2.0 * np.pi) - np.pi


def hover_state(position, yaw: float) -> DroneState:
    """At rest at ``position`` (3,) with heading ``yaw``."""
    return DroneState(np.asarray(position, np.float64).reshape(3).copy(), np.zeros(3),
                      np.zeros(3), float(yaw))


def attitude(a, yaw) -> np.ndarray:
    """(..., 3, 3) ``R_WQ``: thrust axis (Q's z) along ``a - g`` for accelerations ``a``
    (..., 3), Q's x axis the nearest to the heading ``yaw`` (...,) in the plane normal to it."""
    a = np.asarray(a, np.float64)
    yaw = np.asarray(yaw, np.float64)
    thrust = a - np.asarray(GRAVITY_W)
    z = thrust / np.linalg.norm(thrust, axis=-1, keepdims=True)
    heading = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], -1)
    y = np.cross(z, heading)
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], -1)


def _clip_norm(x: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(x))
    return x * (limit / n) if n > limit else x


def fly(start: DroneState, setpoint, yaw_setpoint: float, steps: int,
        config: DroneConfig = DroneConfig(), velocity_ff=None) -> DroneFlight:
    """Fly ``steps`` IMU periods towards a held set-point (the module docstring's law).

    Args:
        start: the state at the first sample.
        setpoint: (3,) world position set-point, metres.
        yaw_setpoint: heading set-point, radians (any branch: the error is wrapped).
        steps: IMU periods to integrate (>= 0).
        config: limits and gains.
        velocity_ff: (3,) velocity feed-forward, m/s (the set-point's own velocity; ``None``:
            zero).

    Returns:
        :class:`DroneFlight` over samples ``0 .. steps``.
    """
    dt, tau = config.dt, config.accel_tau
    sp = np.asarray(setpoint, np.float64).reshape(3)
    ff = np.zeros(3) if velocity_ff is None else np.asarray(velocity_ff, np.float64).reshape(3)
    p, v, a = start.p.astype(np.float64), start.v.astype(np.float64), start.a.astype(np.float64)
    yaw = float(start.yaw)
    P, V, A, Y = [p], [v], [a], [yaw]
    mix = min(dt / tau, 1.0)
    for _ in range(int(steps)):
        v_des = _clip_norm(ff + config.position_gain * (sp - p), config.max_speed)
        a_cmd = _clip_norm(config.velocity_gain * (v_des - v - tau * a), config.max_accel)
        p = p + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        a = a + (a_cmd - a) * mix
        yaw = yaw + float(np.clip(config.yaw_gain * wrap(yaw_setpoint - yaw), -config.max_yaw_rate,
                                  config.max_yaw_rate)) * dt
        P.append(p)
        V.append(v)
        A.append(a)
        Y.append(yaw)
    A_ = np.stack(A)
    Y_ = np.asarray(Y)
    return DroneFlight(np.stack(P), np.stack(V), A_, Y_, attitude(A_, Y_))


def imu_samples(flight: DroneFlight, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact IMU samples (in Q) of a flight's ``n`` steps: ``gyro`` (n, 3) rad/s and
    ``accel`` (n, 3) m/s^2 (the module docstring's zero-order hold)."""
    R = flight.R_WQ
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])  # R_k^T R_{k+1}
    gyro = Rotation.from_matrix(rel).as_rotvec() / dt
    accel = np.einsum("nji,nj->ni", R[:-1], flight.a[:-1] - np.asarray(GRAVITY_W))
    return gyro, accel
