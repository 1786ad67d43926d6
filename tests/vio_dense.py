"""The window's residuals as one dense vector: the reference the structured normal equations
(:func:`uavcal_jax.vio.normal_equations`) and the marginalisation are checked against."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.vio import robust
from uavcal_jax.vio.residuals import factor_residuals
from uavcal_jax.vio.window import FRAME_DIM, CalibParams, WindowProblem, WindowState


def stacked_residuals(state: WindowState, problem: WindowProblem, params: CalibParams
                      ) -> tuple[jax.Array, jax.Array]:
    """``(r, w)``: the whitened residual vector (2M + 15(N-1) + 15N,) before the robust
    function, and the IRLS weight ``rho'(s)`` of each row (0 on masked rows), so that
    ``J^T diag(w) J`` and ``J^T (w r)`` are the Gauss-Newton normal equations and gradient."""
    cfg = problem.config
    res = factor_residuals(state, problem, params)
    s = jnp.sum(res.observation**2, -1)
    w_obs = jnp.where(res.observation_mask, robust.weight(s, cfg.robust, cfg.robust_scale), 0.0)
    r = jnp.concatenate([res.observation.reshape(-1), res.imu.reshape(-1), res.prior])
    w = jnp.concatenate([jnp.repeat(w_obs, 2),
                         jnp.repeat(res.imu_mask.astype(r.dtype), FRAME_DIM),
                         jnp.ones_like(res.prior)])
    return r, w
