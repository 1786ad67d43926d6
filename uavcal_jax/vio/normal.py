"""Structured normal equations of the window and their solution by Schur complement.

Unknowns: the keyframe tangents (N, 15) and the inverse-depth tangents (L,). Every
reprojection residual touches two keyframes' poses and one landmark, every IMU residual two
consecutive keyframes, the prior only keyframes, so the system is::

    [ H_ff    H_fl ] [dx_f]     [g_f]
    [ H_fl^T  H_ll ] [dx_l] = - [g_l]

with ``H_ff`` (15N, 15N) dense, ``H_fl`` (15N, L) and ``H_ll`` (L,) diagonal.

Per-factor blocks come from the small local residuals of :mod:`uavcal_jax.vio.residuals`
(13 columns for an observation: 6 + 6 pose, 1 inverse depth; 30 for an IMU interval): the
observations' Gauss-Newton blocks from their analytic Jacobian
(:func:`~uavcal_jax.vio.residuals.observation_jacobian`, 5x faster on XLA:CPU than ``jacfwd``
of the same residual, which the exact Hessian still uses), the IMU intervals' from ``jacfwd``;
they are accumulated with segment sums. Landmarks are eliminated by the
Schur complement ``S = H_ff - H_fl H_ll^-1 H_fl^T`` and ``S`` (150 x 150 for N = 10) is
factored by Cholesky; the inverse depths follow by back-substitution.

Two Hessians: ``exact=False`` is Gauss-Newton with IRLS weights (``rho' J^T J``, the solver's);
``exact=True`` is the exact Hessian of the cost in the same tangent chart (per-factor
``jax.hessian``), whose landmark block is diagonal too. The implicit gradients need it: the
Gauss-Newton matrix omits the residual curvature, which moves the gradient by up to ~1 %.

Unused keyframe slots get identity rows (their steps are zero) and unused or unobserved
landmarks a unit diagonal, so the factorisation stays defined at every fill level.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from uavcal_jax.vio import robust
from uavcal_jax.vio.residuals import (
    gather_imu,
    gather_observations,
    imu_local,
    imu_mask,
    landmark_mask,
    observation_jacobian,
    observation_local,
    observation_mask,
    prior_residual,
    prior_rotation_local,
)
from uavcal_jax.vio.window import FRAME_DIM, POSE_DIM, CalibParams, WindowProblem, WindowState

__all__ = ["NormalEquations", "normal_equations", "solve_linear", "solve_step"]

_D = FRAME_DIM
_P = POSE_DIM


@dataclasses.dataclass(frozen=True)
class NormalEquations:
    """The assembled system (a pytree).

    Attributes:
        H_ff: (15N, 15N).  H_fl: (15N, L).  H_ll: (L,).
        g_f: (15N,) and g_l: (L,) gradient of the cost.
        cost: () the cost at the linearisation point.
        frame_active: (15N,) bool.  landmark_active: (L,) bool.
    """

    H_ff: jax.Array
    H_fl: jax.Array
    H_ll: jax.Array
    g_f: jax.Array
    g_l: jax.Array
    cost: jax.Array
    frame_active: jax.Array
    landmark_active: jax.Array


jax.tree_util.register_dataclass(
    NormalEquations, data_fields=[f.name for f in dataclasses.fields(NormalEquations)],
    meta_fields=[])


def _local_blocks(fun, dim: int, weight_fn, exact: bool):
    """``(H (dim, dim), g (dim,), cost ())`` of one factor from its local residual ``fun(d)``.

    ``weight_fn(s)`` maps the squared residual to ``(rho(s), rho'(s))``.
    """
    zero = jnp.zeros(dim)

    if exact:
        def cost(d):
            r = fun(d)
            return 0.5 * weight_fn(jnp.sum(r * r))[0]

        grad_and_cost = jax.value_and_grad(cost)
        H = jax.jacfwd(lambda d: grad_and_cost(d)[1])(zero)
        c, g = grad_and_cost(zero)
        return H, g, c

    def both(d):
        r = fun(d)
        return r, r

    J, r = jax.jacfwd(both, has_aux=True)(zero)
    rho, w = weight_fn(jnp.sum(r * r))
    return w * (J.T @ J), w * (J.T @ r), 0.5 * rho


def _prior_blocks(state: WindowState, problem: WindowProblem, exact: bool):
    """``(H (15N, 15N), g (15N,), cost)`` of ``0.5 |r + J d(delta)|^2``, ``d = (x ⊞ delta) ⊟ lin``.

    ``d`` is linear in ``delta`` except for each keyframe's rotation, so
    ``dd/ddelta = blockdiag(Jr^-1-like 3x3, I_12)`` per keyframe and the exact Hessian adds
    ``sum_i (J^T res)_i Hess(d_i)`` over the rotation components only.
    """
    N = problem.frame_mask.shape[0]
    prior = problem.prior
    on = prior.mask.astype(state.frames.position.dtype)
    R, R_lin = state.frames.rotation, prior.lin.rotation
    zero3 = jnp.zeros((N, 3), R.dtype)
    D_rot = jax.vmap(jax.jacfwd(prior_rotation_local, argnums=2))(R, R_lin, zero3)
    D_rot = jnp.where(problem.frame_mask[:, None, None], D_rot, 0.0)
    D = jnp.zeros((N, _D, _D), R.dtype).at[:, 3:, 3:].set(jnp.eye(_D - 3, dtype=R.dtype))
    D = jnp.where(problem.frame_mask[:, None, None], D, 0.0).at[:, :3, :3].set(D_rot)
    D = _block_diag(D)
    res = prior_residual(state.frames, problem)
    Jd = on * (prior.J @ D)
    H = Jd.T @ Jd
    g = Jd.T @ res
    if exact:
        u = (on * (prior.J.T @ res)).reshape(N, _D)[:, :3]
        hess = jax.vmap(jax.hessian(prior_rotation_local, argnums=2))(R, R_lin, zero3)
        curv = jnp.einsum("nc,ncij->nij", u, hess)
        curv = jnp.where(problem.frame_mask[:, None, None], curv, 0.0)
        H = H + _block_diag(jnp.zeros((N, _D, _D), R.dtype).at[:, :3, :3].set(curv))
    return H, g, 0.5 * jnp.sum(res * res)


def _block_diag(blocks: jax.Array) -> jax.Array:
    """(n, d, d) -> (n d, n d) block-diagonal."""
    n, d, _ = blocks.shape
    eye = jnp.eye(n, dtype=blocks.dtype)
    return jnp.einsum("nm,nij->nimj", eye, blocks).reshape(n * d, n * d)


@functools.partial(jax.jit, static_argnames=("exact",))
def normal_equations(state: WindowState, problem: WindowProblem, params: CalibParams,
                     exact: bool = False) -> NormalEquations:
    """Assemble the structured system at ``state`` (see the module docstring)."""
    cfg = problem.config
    N, L, _ = problem.capacities
    dtype = state.frames.position.dtype

    # observations: local variables (pose of the anchor, pose of the observer, inverse depth)
    om = observation_mask(problem)
    g_obs = gather_observations(state, problem, params)

    def obs_blocks(g, use):
        def fun(d):
            return observation_local(g, d[:_P], d[_P:2 * _P], d[2 * _P], cfg)

        def wfn(s):
            return (jnp.where(use, robust.rho(s, cfg.robust, cfg.robust_scale), 0.0),
                    jnp.where(use, robust.weight(s, cfg.robust, cfg.robust_scale), 0.0))
        return _local_blocks(fun, 2 * _P + 1, wfn, exact)

    if exact:
        H13, g13, c_obs = jax.vmap(obs_blocks)(g_obs, om)
    else:
        r, J = observation_jacobian(g_obs, cfg)
        s = jnp.sum(r * r, -1)
        w = jnp.where(om, robust.weight(s, cfg.robust, cfg.robust_scale), 0.0)
        c_obs = 0.5 * jnp.where(om, robust.rho(s, cfg.robust, cfg.robust_scale), 0.0)
        # J^T J and J^T r over the two rows as elementwise products (see residuals._mm)
        H13 = w[:, None, None] * (J[:, 0, :, None] * J[:, 0, None, :]
                                  + J[:, 1, :, None] * J[:, 1, None, :])
        g13 = w[:, None] * (J[:, 0] * r[:, 0:1] + J[:, 1] * r[:, 1:2])
    a = problem.landmarks.anchor[problem.observations.landmark]
    b = problem.observations.frame
    lm = problem.observations.landmark
    pa, pb, il = slice(0, _P), slice(_P, 2 * _P), 2 * _P

    pose_blocks = jnp.concatenate([H13[:, pa, pa], H13[:, pa, pb], H13[:, pb, pa],
                                   H13[:, pb, pb]])
    pair = jnp.concatenate([a * N + a, a * N + b, b * N + a, b * N + b])
    H_pose = jax.ops.segment_sum(pose_blocks, pair, num_segments=N * N).reshape(N, N, _P, _P)
    H_ff = jnp.zeros((N, N, _D, _D), dtype).at[:, :, :_P, :_P].add(H_pose)

    fl = jax.ops.segment_sum(jnp.concatenate([H13[:, pa, il], H13[:, pb, il]]),
                             jnp.concatenate([a * L + lm, b * L + lm]),
                             num_segments=N * L).reshape(N, L, _P)
    H_fl = jnp.zeros((N, _D, L), dtype).at[:, :_P, :].add(jnp.swapaxes(fl, 1, 2))
    H_ll = jax.ops.segment_sum(H13[:, il, il], lm, num_segments=L)
    g_l = jax.ops.segment_sum(g13[:, il], lm, num_segments=L)
    g_pose = jax.ops.segment_sum(jnp.concatenate([g13[:, pa], g13[:, pb]]),
                                 jnp.concatenate([a, b]), num_segments=N)
    g_f = jnp.zeros((N, _D), dtype).at[:, :_P].add(g_pose)

    # IMU intervals k -> k + 1
    im = imu_mask(problem)
    g_imu = gather_imu(state, problem, params)

    def imu_blocks(g, use):
        def fun(d):
            return imu_local(g, d[:_D], d[_D:], cfg)

        def wfn(s):
            on = use.astype(s.dtype)
            return on * s, on
        return _local_blocks(fun, 2 * _D, wfn, exact)

    H30, g30, c_imu = jax.vmap(imu_blocks)(g_imu, im)
    k = jnp.arange(N - 1)
    i_, j_ = slice(0, _D), slice(_D, 2 * _D)
    H_ff = (H_ff.at[k, k].add(H30[:, i_, i_]).at[k, k + 1].add(H30[:, i_, j_])
            .at[k + 1, k].add(H30[:, j_, i_]).at[k + 1, k + 1].add(H30[:, j_, j_]))
    g_f = g_f.at[k].add(g30[:, i_]).at[k + 1].add(g30[:, j_])

    H_ff = jnp.swapaxes(H_ff, 1, 2).reshape(N * _D, N * _D)
    g_f = g_f.reshape(-1)
    H_fl = H_fl.reshape(N * _D, L)

    Hp, gp, c_prior = _prior_blocks(state, problem, exact)
    H_ff = H_ff + Hp
    g_f = g_f + gp

    fa = jnp.repeat(problem.frame_mask, _D)
    la = landmark_mask(problem)
    H_ff = H_ff + jnp.diag(jnp.where(fa, 0.0, 1.0))
    H_ll = jnp.where(la, H_ll, 1.0)
    cost = jnp.sum(c_obs) + jnp.sum(c_imu) + c_prior
    return NormalEquations(H_ff, H_fl, H_ll, g_f, g_l, cost, fa, la)


def solve_linear(neq: NormalEquations, rhs_f: jax.Array, rhs_l: jax.Array,
                 damping=0.0, cholesky: bool = True) -> tuple[jax.Array, jax.Array]:
    """Solve ``(H + damping D) x = rhs`` by eliminating the landmarks (Schur complement).

    ``D = diag(H)`` clipped to ``[1e-6, 1e32]`` (Marquardt). ``cholesky=False`` factors the
    reduced system by LU instead (for the exact Hessian, not guaranteed definite away from a
    minimum). Returns ``(x_f (15N,), x_l (L,))``; inactive entries are zero where ``rhs`` is.
    """
    Hf = neq.H_ff + damping * jnp.diag(jnp.clip(jnp.diag(neq.H_ff), 1e-6, 1e32))
    d = neq.H_ll + damping * jnp.clip(neq.H_ll, 1e-6, 1e32)
    W = neq.H_fl / d[None, :]
    S = Hf - W @ neq.H_fl.T
    b = rhs_f - W @ rhs_l
    # Jacobi equilibration: the frame block mixes millimetre IMU sigmas with micro-unit bias
    # random walks (diagonal entries from 1e2 to 1e12); scaled, the factorisation's error
    # follows the condition number of the equilibrated matrix instead
    s = 1.0 / jnp.sqrt(jnp.clip(jnp.abs(jnp.diag(S)), 1e-300, None))
    S = s[:, None] * S * s[None, :]
    S = 0.5 * (S + S.T)
    if cholesky:
        x_f = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(S, lower=True), s * b)
    else:
        x_f = jnp.linalg.solve(S, s * b)
    x_f = s * x_f
    x_l = (rhs_l - neq.H_fl.T @ x_f) / d
    return x_f, x_l


def solve_step(neq: NormalEquations, damping=0.0) -> tuple[jax.Array, jax.Array]:
    """The (damped) Gauss-Newton step ``(dx_f (N, 15), dx_l (L,))``."""
    x_f, x_l = solve_linear(neq, -neq.g_f, -neq.g_l, damping)
    N = x_f.shape[0] // _D
    return x_f.reshape(N, _D), x_l
