"""The reference solve: jaxopt's Gauss-Newton / Levenberg-Marquardt on the flattened residual.

Same cost as the structured solver (:func:`~uavcal_jax.vio.residuals.flat_residual`, whose half
squared norm is the window cost, robust kernel included), minimised over the tangent
perturbation ``z`` of the warm start, ``state ⊞ (s * z)``. ``s`` is the Jacobi scaling
``1 / sqrt(diag(H))`` of the Gauss-Newton matrix at the warm start: the IMU rows are whitened
by millimetre-level sigmas and the bias rows by micro-units, so the unscaled normal
equations have a condition number near 1e14, on which jaxopt's conjugate-gradient inner solve
stalls. The scaling changes the path, not the optimum. Generic and slow (about 100x the
structured solve on a full window): for tests and benchmarks.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import jaxopt

from uavcal_jax.vio.normal import normal_equations
from uavcal_jax.vio.residuals import flat_residual, window_cost
from uavcal_jax.vio.solver import SolveInfo
from uavcal_jax.vio.window import FRAME_DIM, CalibParams, WindowProblem, WindowState, retract

__all__ = ["METHODS", "JaxoptSolver"]

#: jaxopt methods behind :class:`JaxoptSolver`.
METHODS = ("gauss_newton", "levenberg_marquardt")


def _unflatten(z, N):
    return z[:N * FRAME_DIM].reshape(N, FRAME_DIM), z[N * FRAME_DIM:]


def _residual(z, scale, state, problem, params):
    N = problem.frame_mask.shape[0]
    d_f, d_l = _unflatten(z * scale, N)
    return flat_residual(retract(state, d_f, d_l), problem, params)


@dataclasses.dataclass(frozen=True)
class JaxoptSolver:
    """:class:`~uavcal_jax.vio.solver.Solver` calling jaxopt.

    Attributes:
        method: ``"gauss_newton"`` (``jaxopt.GaussNewton``, matrix-free CG inner solve) or
            ``"levenberg_marquardt"`` (materialised Jacobian, Cholesky).
        maxiter: outer iterations at most.
        tol: jaxopt's stopping tolerance (step norm for Gauss-Newton, gradient norm for
            Levenberg-Marquardt, both in the scaled variables).
    """

    method: str = "gauss_newton"
    maxiter: int = 50
    tol: float = 1e-10

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")

    def __call__(self, state: WindowState, problem: WindowProblem, params: CalibParams
                 ) -> tuple[WindowState, SolveInfo]:
        return _run(self, state, problem, params)


@jax.jit
def _scale(state, problem, params):
    neq = normal_equations(state, problem, params)
    h = jnp.concatenate([jnp.diag(neq.H_ff), neq.H_ll])
    return 1.0 / jnp.sqrt(jnp.maximum(h, 1e-12))


@functools.partial(jax.jit, static_argnums=0)
def _run(solver: JaxoptSolver, state, problem, params):
    scale = _scale(state, problem, params)
    if solver.method == "gauss_newton":
        opt = jaxopt.GaussNewton(residual_fun=_residual, maxiter=solver.maxiter,
                                 tol=solver.tol, implicit_diff=False)
    else:
        opt = jaxopt.LevenbergMarquardt(residual_fun=_residual, maxiter=solver.maxiter,
                                        tol=solver.tol, xtol=solver.tol, gtol=solver.tol,
                                        solver="cholesky", materialize_jac=True,
                                        implicit_diff=False)
    z0 = jnp.zeros_like(scale)
    z, st = opt.run(z0, scale, state, problem, params)
    d_f, d_l = _unflatten(z * scale, problem.frame_mask.shape[0])
    out = retract(state, d_f, d_l)
    info = SolveInfo(jnp.asarray(st.iter_num, jnp.int32), window_cost(state, problem, params),
                     window_cost(out, problem, params), jnp.asarray(st.iter_num < solver.maxiter))
    return out, info
