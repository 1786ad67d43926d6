"""Navigation state, state prediction and the 15-dimensional IMU residual (the VIO's IMU factor).

The world frame is z up with gravity :data:`~uavcal_jax.geometry.frames.GRAVITY_W`,
``(0, 0, -9.81)`` (GTSAM's ``MakeSharedU(9.81)``); the
body frame is the IMU frame; ``rotation`` maps body to world.

Prediction (Forster et al. eq. 33; GTSAM's ``PreintegrationBase::predict`` without Coriolis)::

    R_j = R_i dR(b)
    v_j = v_i + g dt + R_i dv(b)
    p_j = p_i + v_i dt + g dt^2 / 2 + R_i dp(b)

with the bias-corrected deltas of :func:`~uavcal_jax.imu.preintegration.bias_correct`.

Residual (Forster et al. eq. 45, then the bias random walk), order rotation, velocity,
position, gyro bias, accel bias::

    r_R  = log(dR(b_i)^T R_i^T R_j)
    r_v  = R_i^T (v_j - v_i - g dt) - dv(b_i)
    r_p  = R_i^T (p_j - p_i - v_i dt - g dt^2 / 2) - dp(b_i)
    r_bg = bg_j - bg_i,   r_ba = ba_j - ba_i

:func:`imu_residual_whitened` returns ``L^-1 r`` with ``L L^T`` the residual covariance:
the propagated covariance (for the tangent scheme mapped from ``theta`` to the rotation's
right perturbation through ``Jr(theta)``) and the random-walk covariance of the biases (or the
full 15x15 with its correlations when the preintegration was run with
``bias_covariance=True``). Its squared norm is the factor's cost (Mahalanobis distance).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from uavcal_jax.geometry import so3
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.preintegration import Preintegrated, bias_correct

__all__ = [
    "NavState",
    "ImuBias",
    "predict",
    "imu_residual",
    "residual_covariance",
    "imu_residual_whitened",
]

@dataclasses.dataclass(frozen=True)
class NavState:
    """Body pose and velocity in the world frame (a pytree; leading batch axes allowed).

    Attributes:
        rotation: (..., 3, 3) body-to-world rotation.
        position: (..., 3) m.
        velocity: (..., 3) m/s, world frame.
    """

    rotation: jax.Array
    position: jax.Array
    velocity: jax.Array

    @classmethod
    def from_quaternion(cls, wxyz, position, velocity) -> NavState:
        """From a body-to-world quaternion (w, x, y, z), as in EuRoC's ground truth."""
        return cls(so3.from_quaternion(jnp.asarray(wxyz)), jnp.asarray(position),
                   jnp.asarray(velocity))


@dataclasses.dataclass(frozen=True)
class ImuBias:
    """Gyro and accelerometer biases (a pytree). ``gyro``: (..., 3) rad/s; ``accel``: m/s^2."""

    gyro: jax.Array
    accel: jax.Array

    @property
    def vector(self) -> jax.Array:
        """(..., 6): gyro then accel."""
        return jnp.concatenate([jnp.asarray(self.gyro), jnp.asarray(self.accel)], axis=-1)


for _cls, _fields in ((NavState, ["rotation", "position", "velocity"]),
                      (ImuBias, ["gyro", "accel"])):
    jax.tree_util.register_dataclass(_cls, data_fields=_fields, meta_fields=[])


def _as_bias(bias, pim: Preintegrated) -> tuple[jax.Array, jax.Array]:
    """``(gyro, accel)`` from ImuBias, a (gyro, accel) pair, a (..., 6) array or None."""
    if bias is None:
        return pim.bias_gyro, pim.bias_accel
    if isinstance(bias, ImuBias):
        return jnp.asarray(bias.gyro), jnp.asarray(bias.accel)
    if isinstance(bias, (tuple, list)):
        return jnp.asarray(bias[0]), jnp.asarray(bias[1])
    bias = jnp.asarray(bias)
    return bias[..., :3], bias[..., 3:]


def _mv(m, x):
    return jnp.einsum("...ij,...j->...i", m, x)


def _mtv(m, x):
    return jnp.einsum("...ji,...j->...i", m, x)


def predict(state_i: NavState, pim: Preintegrated, bias=None, gravity=GRAVITY_W) -> NavState:
    """State at ``t_j`` from the state at ``t_i``, the preintegration and the bias at ``t_i``.

    Args:
        state_i: :class:`NavState` at ``t_i``.
        pim: :class:`~uavcal_jax.imu.preintegration.Preintegrated` over ``[t_i, t_j]``.
        bias: :class:`ImuBias`, ``(gyro, accel)`` or a (..., 6) array; ``None`` means the
            biases the samples were integrated with. Other biases are applied to first order.
        gravity: (3,) world gravity.
    """
    bg, ba = _as_bias(bias, pim)
    dR, dv, dp = bias_correct(pim, bg, ba)
    g = jnp.asarray(gravity, dv.dtype)
    dt = pim.delta_t[..., None]
    R_i = state_i.rotation
    rotation = R_i @ dR
    velocity = state_i.velocity + g * dt + _mv(R_i, dv)
    position = state_i.position + state_i.velocity * dt + 0.5 * g * dt * dt + _mv(R_i, dp)
    return NavState(rotation, position, velocity)


def imu_residual(state_i: NavState, bias_i, state_j: NavState, bias_j, pim: Preintegrated,
                 gravity=GRAVITY_W) -> jax.Array:
    """Unwhitened 15-vector (rotation, velocity, position, gyro bias, accel bias), (..., 15).

    ``bias_i``, ``bias_j``: :class:`ImuBias`, ``(gyro, accel)`` pairs or (..., 6) arrays.
    """
    bg_i, ba_i = _as_bias(bias_i, pim)
    bg_j, ba_j = _as_bias(bias_j, pim)
    dR, dv, dp = bias_correct(pim, bg_i, ba_i)
    g = jnp.asarray(gravity, dv.dtype)
    dt = pim.delta_t[..., None]
    R_i = state_i.rotation
    r_R = so3.log(jnp.swapaxes(dR, -1, -2) @ jnp.swapaxes(R_i, -1, -2) @ state_j.rotation)
    r_v = _mtv(R_i, state_j.velocity - state_i.velocity - g * dt) - dv
    r_p = _mtv(R_i, state_j.position - state_i.position - state_i.velocity * dt
               - 0.5 * g * dt * dt) - dp
    return jnp.concatenate([r_R, r_v, r_p, bg_j - bg_i, ba_j - ba_i], axis=-1)


def residual_covariance(pim: Preintegrated) -> jax.Array:
    """(..., 15, 15) covariance of :func:`imu_residual` (order rotation, velocity, position,
    gyro bias, accel bias).

    The rotation part of the tangent scheme's ``cov`` (of ``theta``) is mapped to the right
    perturbation of ``delta_R`` with ``Jr(theta)``. The residual's delta rows are "predicted
    minus measured", so their correlation with the bias rows changes sign relative to ``cov``
    (which describes the measurement error).
    """
    cov = pim.cov
    dtype = cov.dtype
    batch = cov.shape[:-2]
    J = jnp.broadcast_to(jnp.eye(9, dtype=dtype), batch + (9, 9))
    if pim.scheme == "tangent":
        J = J.at[..., :3, :3].set(so3.right_jacobian(pim.theta))
    if cov.shape[-1] == 15:
        J = jnp.concatenate(
            [jnp.concatenate([-J, jnp.zeros(batch + (9, 6), dtype)], -1),
             jnp.concatenate([jnp.zeros(batch + (6, 9), dtype),
                              jnp.broadcast_to(jnp.eye(6, dtype=dtype), batch + (6, 6))], -1)],
            -2,
        )
        return J @ cov @ jnp.swapaxes(J, -1, -2)
    c9 = J @ cov @ jnp.swapaxes(J, -1, -2)
    top = jnp.concatenate([c9, jnp.zeros(batch + (9, 6), dtype)], -1)
    bot = jnp.concatenate([jnp.zeros(batch + (6, 9), dtype), pim.cov_bias], -1)
    return jnp.concatenate([top, bot], -2)


def imu_residual_whitened(state_i: NavState, bias_i, state_j: NavState, bias_j,
                          pim: Preintegrated, gravity=GRAVITY_W, jitter: float = 0.0
                          ) -> jax.Array:
    """``L^-1 r`` (..., 15) with ``L L^T = residual_covariance(pim) + jitter I``.

    The bias rows need non-zero random-walk densities (a constant bias has zero covariance:
    pass ``jitter`` or drop those rows, ``[..., :9]``, and whiten with ``cov[:9, :9]`` alone).
    """
    r = imu_residual(state_i, bias_i, state_j, bias_j, pim, gravity)
    cov = residual_covariance(pim)
    if jitter:
        cov = cov + jitter * jnp.eye(15, dtype=cov.dtype)
    L = jnp.linalg.cholesky(cov)
    return jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]
