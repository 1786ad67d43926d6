"""IMU-only dead reckoning: integrate gyro and accelerometer samples from a known initial
state into a world trajectory (strapdown navigation, no other sensor).

Frames and units: the body frame is the IMU frame; the world frame is z up with gravity
``GRAVITY_W = (0, 0, -9.81)`` m/s^2 (:mod:`uavcal_jax.geometry.frames`). ``R`` is body-to-world,
``v`` and ``p`` are the body's world velocity (m/s) and position (m); gyro in rad/s and
accelerometer (specific force) in m/s^2, both in the body frame, as the simulator writes them
(``accel = R^T (a_W - g_W)``).

Scheme (per step ``k -> k+1`` of length ``dt_k``; second order, exact for a constant body rate
and a world acceleration linear over the step)::

    R_{k+1} = R_k Exp(dt_k (w_k + w_{k+1}) / 2)
    a_k     = R_k f_k + g_W                                  (world acceleration)
    v_{k+1} = v_k + dt_k (a_k + a_{k+1}) / 2
    p_{k+1} = p_k + dt_k v_k + dt_k^2 (2 a_k + a_{k+1}) / 6

A constant accelerometer error ``b`` (world-fixed attitude) makes the position drift by
``b t^2 / 2``; a gyro error ``w`` tilts the attitude by ``w t``, which leaks gravity into the
horizontal and grows the position error as ``g w t^3 / 6``. Run it under
``jax.enable_x64(True)`` for long flights: float32 loses millimetres within seconds.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.geometry import so3
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.offset import remove_offset

__all__ = ["dead_reckon"]


@jax.jit
def dead_reckon(dt, gyro, accel, R0, v0, p0, offset=None):
    """Integrate IMU samples from the state ``(R0, v0, p0)`` at the first sample.

    Args:
        dt: ``(N - 1,)`` seconds from sample ``k`` to ``k + 1`` (positive).
        gyro: ``(N, 3)`` body angular rate, rad/s, body frame.
        accel: ``(N, 3)`` specific force, m/s^2, body frame.
        R0: ``(3, 3)`` body-to-world rotation at sample 0.
        v0: ``(3,)`` world velocity at sample 0, m/s.
        p0: ``(3,)`` world position at sample 0, m.
        offset: ``(6,)`` constant IMU error to subtract first (gyro rad/s, accel m/s^2;
            :func:`uavcal_jax.imu.offset.remove_offset`), or ``None``.

    Returns:
        ``(R, v, p)``: ``(N, 3, 3)``, ``(N, 3)``, ``(N, 3)`` the state at every sample
        (sample 0 is the initial state).
    """
    gyro, accel = jnp.asarray(gyro), jnp.asarray(accel)
    if offset is not None:
        gyro, accel = remove_offset(gyro, accel, offset)
    g = jnp.asarray(GRAVITY_W, accel.dtype)
    R0 = jnp.asarray(R0, accel.dtype)
    a0 = R0 @ accel[0] + g

    def step(state, inputs):
        R, v, p, a = state
        h, w0, w1, f1 = inputs
        R1 = R @ so3.exp(0.5 * h * (w0 + w1))
        a1 = R1 @ f1 + g
        v1 = v + 0.5 * h * (a + a1)
        p1 = p + h * v + h * h * (2.0 * a + a1) / 6.0
        return (R1, v1, p1, a1), (R1, v1, p1)

    init = (R0, jnp.asarray(v0, accel.dtype), jnp.asarray(p0, accel.dtype), a0)
    _, (R, v, p) = jax.lax.scan(step, init, (jnp.asarray(dt, accel.dtype), gyro[:-1], gyro[1:],
                                             accel[1:]))
    return (jnp.concatenate([init[0][None], R]), jnp.concatenate([init[1][None], v]),
            jnp.concatenate([init[2][None], p]))
