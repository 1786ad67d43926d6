"""Residuals and cost of the sliding window (RPEOD eqs. 7-9).

Three kinds of factor, each whitened so that its cost is half a squared norm:

* **Reprojection** (VINS-Fusion's ``ProjectionTwoFrameTwoCamFactor``): landmark ``l`` with
  inverse depth ``rho`` and bearing ``(x, y, 1)`` in camera 0 of its anchor keyframe ``a``,
  observed in camera ``c`` of keyframe ``b``::

      P_a = (x, y, 1) / rho                     anchor camera frame
      P_w = R_a (R_BC0 P_a + t_BC0) + p_a        world
      P_c = R_BCc^T (R_b^T (P_w - p_b) - t_BCc)  observing camera
      r   = (P_c[:2] / P_c[2] - xy_obs) * focal / sigma_px

  under the robust function of :mod:`uavcal_jax.vio.robust` (cost ``0.5 rho(|r|^2)``).
  ``b == a`` with ``c == 1`` is the stereo residual (VINS-Fusion's OneFrameTwoCam factor).
* **IMU** between keyframes ``k`` and ``k + 1``:
  :func:`uavcal_jax.imu.imu_residual_whitened` (15 rows: rotation, velocity, position, gyro
  and accel bias random walk), with the calibration offset added to the biases it reads
  (see :class:`~uavcal_jax.vio.window.CalibParams`).
* **Prior**: ``r_p + J_p vec(frames ⊟ lin)`` (the linear marginalisation prior).

The "local" functions take one factor's gathered inputs and the tangent perturbations of
the variables it touches; the solver differentiates them (per block), and the batched
functions evaluate them at zero, so both read the same arithmetic.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from uavcal_jax.geometry import so3
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu import NavState, imu_residual_whitened
from uavcal_jax.vio import robust
from uavcal_jax.vio.window import (
    BA,
    BG,
    POS,
    ROT,
    VEL,
    CalibParams,
    Keyframes,
    WindowProblem,
    WindowState,
    frame_difference,
    retract,
)

__all__ = [
    "FactorResiduals",
    "flat_residual",
    "gather_imu",
    "gather_observations",
    "imu_local",
    "imu_mask",
    "landmark_mask",
    "observation_jacobian",
    "observation_local",
    "observation_mask",
    "prior_rotation_local",
    "prior_residual",
    "factor_residuals",
    "tangent_cost",
    "window_cost",
]


# 3x3 products as broadcast multiply-adds rather than dot_general: vmapped over thousands of
# observations and their Jacobian columns, XLA's CPU batched dot of 3x3 blocks is several
# times slower than the elementwise form


def _mv(m, x):
    return jnp.sum(m * x[..., None, :], axis=-1)


def _mtv(m, x):
    return jnp.sum(m * x[..., :, None], axis=-2)


def _mm(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _exp2(phi):
    """``I + W + W^2 / 2`` (``W = hat(phi)``): the local functions are only differentiated at
    ``phi = 0``, where this truncation has the first and second derivatives of ``exp`` (so the
    Gauss-Newton Jacobian and the exact Hessian are unchanged) at a fraction of the compile
    cost of the full exponential."""
    W = so3.hat(phi)
    return jnp.eye(3, dtype=W.dtype) + W + 0.5 * _mm(W, W)


# --- masks -----------------------------------------------------------------------------------


def observation_mask(problem: WindowProblem) -> jax.Array:
    """(M,) bool: observation in use, and its keyframe, anchor and landmark too."""
    obs, lm, fm = problem.observations, problem.landmarks, problem.frame_mask
    anchor = lm.anchor[obs.landmark]
    return obs.mask & fm[obs.frame] & fm[anchor] & lm.mask[obs.landmark]


def landmark_mask(problem: WindowProblem) -> jax.Array:
    """(L,) bool: landmark in use with at least one observation in use (otherwise its inverse
    depth is unconstrained and the solver leaves it alone)."""
    L = problem.landmarks.mask.shape[0]
    count = jax.ops.segment_sum(observation_mask(problem).astype(jnp.int32),
                                problem.observations.landmark, num_segments=L)
    return problem.landmarks.mask & (count > 0)


def imu_mask(problem: WindowProblem) -> jax.Array:
    """(N - 1,) bool: interval in use and both its keyframes too."""
    fm = problem.frame_mask
    return problem.imu.mask & fm[:-1] & fm[1:]


# --- reprojection ----------------------------------------------------------------------------


def gather_observations(state: WindowState, problem: WindowProblem, params: CalibParams
                        ) -> dict[str, jax.Array]:
    """Per-observation inputs of the reprojection residual, each with leading axis ``M``."""
    obs, lm, fr = problem.observations, problem.landmarks, state.frames
    a = lm.anchor[obs.landmark]
    b = obs.frame
    return {
        "R_a": fr.rotation[a], "p_a": fr.position[a],
        "R_b": fr.rotation[b], "p_b": fr.position[b],
        "R_C0": jnp.broadcast_to(params.R_BC[0], (a.shape[0], 3, 3)),
        "t_C0": jnp.broadcast_to(params.t_BC[0], (a.shape[0], 3)),
        "R_Cc": params.R_BC[obs.camera], "t_Cc": params.t_BC[obs.camera],
        "bearing": lm.bearing[obs.landmark], "inv_depth": state.inv_depth[obs.landmark],
        "xy": obs.xy,
    }


def _anchor_point(g: dict) -> jax.Array:
    """The landmark in the anchor keyframe's body frame, (..., 3)."""
    P_a = jnp.concatenate([g["bearing"], jnp.ones_like(g["bearing"][..., :1])], -1)
    P_a = P_a / g["inv_depth"][..., None]
    return _mv(g["R_C0"], P_a) + g["t_C0"]


def _observe(u: jax.Array, g: dict, config) -> jax.Array:
    """Whitened residual (..., 2) of the landmark at ``u`` in the observing body frame."""
    P_c = _mtv(g["R_Cc"], u - g["t_Cc"])
    z = P_c[..., 2:]
    z = jnp.where(z > config.min_depth, z, config.min_depth)
    return (P_c[..., :2] / z - g["xy"]) * config.sqrt_info


def _reproject(g: dict, config) -> jax.Array:
    """Whitened reprojection residual (..., 2) of gathered inputs (see the module docstring)."""
    P_w = _mv(g["R_a"], _anchor_point(g)) + g["p_a"]
    return _observe(_mtv(g["R_b"], P_w - g["p_b"]), g, config)


def _rotate2(d: jax.Array, v: jax.Array) -> jax.Array:
    """``exp(d) v`` to second order, ``v + d x v + (d x (d x v)) / 2``: see :func:`_exp2`; on a
    vector it needs no 3x3 products."""
    dv = jnp.cross(d, v)
    return v + dv + 0.5 * jnp.cross(d, dv)


def observation_local(g: dict, d_a: jax.Array, d_b: jax.Array, d_l: jax.Array, config
                      ) -> jax.Array:
    """Residual (2,) of one observation (unbatched ``g``) at pose perturbations ``d_a``,
    ``d_b`` (6,) (:data:`~uavcal_jax.vio.window.ROT` then ``POS``) of its anchor and observing
    keyframes and ``d_l`` () of its inverse depth.

    ``R exp(d)`` is applied to vectors, ``R exp(d) v = R (exp(d) v)`` and
    ``(R exp(d))^T y = exp(-d) R^T y``, with the second-order :func:`_rotate2`.
    """
    g = dict(g, inv_depth=g["inv_depth"] + d_l)
    P_w = _mv(g["R_a"], _rotate2(d_a[ROT], _anchor_point(g))) + g["p_a"] + d_a[POS]
    u = _rotate2(-d_b[ROT], _mtv(g["R_b"], P_w - g["p_b"] - d_b[POS]))
    return _observe(u, g, config)


def _skew_rows(v: jax.Array) -> jax.Array:
    """``hat(v)`` (..., 3, 3) built elementwise."""
    o = jnp.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                      jnp.stack([-y, x, o], -1)], -2)


def observation_jacobian(g: dict, config) -> tuple[jax.Array, jax.Array]:
    """Whitened residuals (..., 2) and their analytic Jacobians (..., 2, 13) with respect to
    :func:`observation_local`'s perturbations ``(d_a (6,), d_b (6,), d_l ())`` at zero.

    The chain (module docstring) with right perturbations: ``dP_w/dd_a = [-R_a hat(f), I]``
    (``f`` the point in the anchor body), ``du/dd_b = [hat(u), -R_b^T]``, ``du/dP_w = R_b^T``,
    ``dP_w/drho = -R_a R_C0 (x, y, 1) / rho^2``, then the projection. A depth clamped at
    ``min_depth`` has zero derivative, as in the residual. The Gauss-Newton solve uses this
    instead of ``jacfwd`` of :func:`observation_local`, which on XLA:CPU costs several times the
    arithmetic (tests check the two agree)."""
    f = _anchor_point(g)
    P_w = _mv(g["R_a"], f) + g["p_a"]
    u = _mtv(g["R_b"], P_w - g["p_b"])
    P_c = _mtv(g["R_Cc"], u - g["t_Cc"])
    z_raw = P_c[..., 2]
    clamped = z_raw <= config.min_depth
    z = jnp.where(clamped, config.min_depth, z_raw)
    s = config.sqrt_info
    r = (P_c[..., :2] / z[..., None] - g["xy"]) * s
    inv_z = s / z
    zero = jnp.zeros_like(z)
    dz = jnp.where(clamped, 0.0, -inv_z / z)
    # d r / d P_c, (..., 2, 3)
    d_proj = jnp.stack([jnp.stack([inv_z, zero, P_c[..., 0] * dz], -1),
                        jnp.stack([zero, inv_z, P_c[..., 1] * dz], -1)], -2)
    A = _mm(d_proj, jnp.swapaxes(g["R_Cc"], -1, -2))  # d r / d u
    B = _mm(A, jnp.swapaxes(g["R_b"], -1, -2))  # d r / d P_w
    J_a_rot = -_mm(_mm(B, g["R_a"]), _skew_rows(f))
    J_b_rot = _mm(A, _skew_rows(u))
    bearing_h = jnp.concatenate([g["bearing"], jnp.ones_like(g["bearing"][..., :1])], -1)
    rho = g["inv_depth"][..., None]
    dPw_drho = -_mv(g["R_a"], _mv(g["R_C0"], bearing_h)) / (rho * rho)
    J_l = jnp.sum(B * dPw_drho[..., None, :], -1)
    J = jnp.concatenate([J_a_rot, B, J_b_rot, -B, J_l[..., None]], -1)
    return r, J


# --- IMU -------------------------------------------------------------------------------------


def gather_imu(state: WindowState, problem: WindowProblem, params: CalibParams) -> dict:
    """Per-interval inputs of the IMU residual (leading axis ``N - 1``). Unused intervals get a
    unit covariance so that whitening stays finite (their rows are masked)."""
    fr = state.frames
    use = imu_mask(problem)
    pim = problem.imu.pim
    eye = jnp.eye(pim.cov.shape[-1], dtype=pim.cov.dtype)
    pim = dataclasses.replace(
        pim,
        cov=jnp.where(use[:, None, None], pim.cov, eye),
        cov_bias=jnp.where(use[:, None, None], pim.cov_bias, jnp.eye(6, dtype=pim.cov.dtype)),
        delta_t=jnp.where(use, pim.delta_t, 1.0),
    )

    def part(x, lo):
        return x[:-1] if lo else x[1:]

    out = {"pim": pim, "offset": jnp.broadcast_to(params.imu_offset, (use.shape[0], 6))}
    for name, lo in (("i", True), ("j", False)):
        out[name] = jnp.concatenate(
            [part(fr.position, lo), part(fr.velocity, lo), part(fr.bias_gyro, lo),
             part(fr.bias_accel, lo)], -1)
        out["R_" + name] = part(fr.rotation, lo)
    return out


def _imu_whitened(R_i, x_i, R_j, x_j, pim, offset, config) -> jax.Array:
    """``x`` = (position, velocity, bias gyro, bias accel) (..., 12)."""
    s_i = NavState(R_i, x_i[..., 0:3], x_i[..., 3:6])
    s_j = NavState(R_j, x_j[..., 0:3], x_j[..., 3:6])
    return imu_residual_whitened(s_i, x_i[..., 6:12] + offset, s_j, x_j[..., 6:12] + offset,
                                 pim, gravity=GRAVITY_W, jitter=config.imu_jitter)


def _nonrot(d):
    return jnp.concatenate([d[..., POS], d[..., VEL], d[..., BG], d[..., BA]], -1)


def imu_local(g: dict, d_i: jax.Array, d_j: jax.Array, config) -> jax.Array:
    """Whitened residual (15,) of one interval (unbatched ``g``) at keyframe perturbations
    ``d_i``, ``d_j`` (15,)."""
    return _imu_whitened(g["R_i"] @ _exp2(d_i[ROT]), g["i"] + _nonrot(d_i),
                         g["R_j"] @ _exp2(d_j[ROT]), g["j"] + _nonrot(d_j),
                         g["pim"], g["offset"], config)


# --- prior -----------------------------------------------------------------------------------


def prior_residual(frames: Keyframes, problem: WindowProblem) -> jax.Array:
    """(15N,) whitened prior residual; zero when the prior is unused. Unused keyframe slots
    contribute no difference."""
    prior = problem.prior
    diff = frame_difference(frames, prior.lin)
    diff = jnp.where(problem.frame_mask[:, None], diff, 0.0).reshape(-1)
    return jnp.where(prior.mask, prior.r + prior.J @ diff, 0.0)


# --- the window ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FactorResiduals:
    """Whitened residuals before the robust function, masked rows zeroed.

    Attributes:
        observation: (M, 2).  observation_mask: (M,) bool.
        imu: (N - 1, 15).  imu_mask: (N - 1,) bool.
        prior: (15N,).
    """

    observation: jax.Array
    observation_mask: jax.Array
    imu: jax.Array
    imu_mask: jax.Array
    prior: jax.Array


jax.tree_util.register_dataclass(
    FactorResiduals, data_fields=[f.name for f in dataclasses.fields(FactorResiduals)],
    meta_fields=[])


def factor_residuals(state: WindowState, problem: WindowProblem, params: CalibParams
              ) -> FactorResiduals:
    """All whitened residuals of the window."""
    cfg = problem.config
    om = observation_mask(problem)
    r_obs = jnp.where(om[:, None], _reproject(gather_observations(state, problem, params), cfg),
                      0.0)
    im = imu_mask(problem)
    g = gather_imu(state, problem, params)
    r_imu = jnp.where(im[:, None],
                      _imu_whitened(g["R_i"], g["i"], g["R_j"], g["j"], g["pim"], g["offset"],
                                    cfg), 0.0)
    return FactorResiduals(r_obs, om, r_imu, im, prior_residual(state.frames, problem))


def window_cost(state: WindowState, problem: WindowProblem, params: CalibParams) -> jax.Array:
    """The window cost (): ``0.5 sum rho(|r_obs|^2) + 0.5 |r_imu|^2 + 0.5 |r_prior|^2``."""
    cfg = problem.config
    res = factor_residuals(state, problem, params)
    s = jnp.sum(res.observation**2, -1)
    vis = jnp.where(res.observation_mask, robust.rho(s, cfg.robust, cfg.robust_scale), 0.0)
    return 0.5 * (jnp.sum(vis) + jnp.sum(res.imu**2) + jnp.sum(res.prior**2))


def flat_residual(state: WindowState, problem: WindowProblem, params: CalibParams) -> jax.Array:
    """Residual vector whose half squared norm is :func:`window_cost`: each observation's
    rows scaled by ``sqrt(rho(s) / s)``, so generic least-squares solvers (jaxopt) minimise
    the same robust cost."""
    cfg = problem.config
    res = factor_residuals(state, problem, params)
    s = jnp.sum(res.observation**2, -1)
    scale = robust.equivalent_scale(s, cfg.robust, cfg.robust_scale)
    return jnp.concatenate([(res.observation * scale[:, None]).reshape(-1),
                            res.imu.reshape(-1), res.prior])


def tangent_cost(delta_frames: jax.Array, delta_inv_depth: jax.Array, state: WindowState,
                 problem: WindowProblem, params: CalibParams) -> jax.Array:
    """:func:`window_cost` at ``state ⊞ delta`` (for derivatives in the tangent chart)."""
    return window_cost(retract(state, delta_frames, delta_inv_depth), problem, params)


def prior_rotation_local(R: jax.Array, R_lin: jax.Array, d: jax.Array) -> jax.Array:
    """Rotation part (3,) of ``(R ⊞ d) ⊟ R_lin`` for one keyframe; the prior's only nonlinear
    piece (every other component of ``frames ⊟ lin`` is linear in the perturbation)."""
    return so3.log(R_lin.T @ R @ _exp2(d))

