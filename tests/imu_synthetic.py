"""A closed-form synthetic flight for IMU tests: exact samples and exact states (NumPy).

Body-to-world rotation ``R(t) = exp(phi(t))`` and world position ``p(t)`` are smooth closed
forms; the gyro reads ``Jr(phi) phi'`` (body rate) and the accelerometer ``R^T (p'' - g)``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.geometry.frames import GRAVITY_W

G = np.asarray(GRAVITY_W)


def _hat(v):
    x, y, z = v
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def _jr(phi):
    t = np.linalg.norm(phi)
    W = _hat(phi)
    if t < 1e-8:
        return np.eye(3) - 0.5 * W
    return np.eye(3) - (1 - np.cos(t)) / t**2 * W + (t - np.sin(t)) / t**3 * W @ W


def phi(t, rate=1.0):
    return rate * np.stack([0.3 * np.sin(t), 0.4 * t, 0.5 * np.cos(0.7 * t) - 0.5], -1)


def dphi(t, rate=1.0):
    return rate * np.stack([0.3 * np.cos(t), 0.4 * np.ones_like(t), -0.35 * np.sin(0.7 * t)], -1)


def position(t):
    return np.stack([np.sin(1.3 * t), 0.5 * np.cos(t), 0.2 * t**2], -1)


def velocity(t):
    return np.stack([1.3 * np.cos(1.3 * t), -0.5 * np.sin(t), 0.4 * t], -1)


def acceleration(t):
    return np.stack([-1.69 * np.sin(1.3 * t), -0.5 * np.cos(t), 0.4 * np.ones_like(t)], -1)


def rotation(t, rate=1.0):
    return Rotation.from_rotvec(phi(np.atleast_1d(t), rate)).as_matrix()


def imu(t, rate=1.0):
    """Exact (gyro, accel) at times ``t`` (N,)."""
    t = np.atleast_1d(t)
    ph, dph = phi(t, rate), dphi(t, rate)
    gyro = np.stack([_jr(p) @ d for p, d in zip(ph, dph, strict=True)])
    R = rotation(t, rate)
    accel = np.einsum("nji,nj->ni", R, acceleration(t) - G)
    return gyro, accel


def window(t0, duration, rate_hz, rate=1.0):
    """Samples on ``[t0, t0 + duration)`` held for ``1/rate_hz`` each (midpoint values, so the
    zero-order hold is second-order accurate)."""
    n = int(round(duration * rate_hz))
    h = 1.0 / rate_hz
    tk = t0 + h * (np.arange(n) + 0.5)
    gyro, accel = imu(tk, rate)
    return np.full(n, h), gyro, accel


def true_delta(t0, t1, rate=1.0):
    """(delta_R, delta_v, delta_p) of the true motion from t0 to t1."""
    Ri, Rj = rotation(t0, rate)[0], rotation(t1, rate)[0]
    dt = t1 - t0
    vi, vj = velocity(np.array([t0]))[0], velocity(np.array([t1]))[0]
    pi, pj = position(np.array([t0]))[0], position(np.array([t1]))[0]
    return (Ri.T @ Rj, Ri.T @ (vj - vi - G * dt), Ri.T @ (pj - pi - vi * dt - 0.5 * G * dt * dt))
