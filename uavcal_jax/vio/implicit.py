"""Gradients through the window solve by implicit differentiation (no unrolled iterations).

At the solution ``x*(theta)`` of ``min_x f(x, theta)`` (``theta``: the calibration
parameters and any float data of the problem) the tangent-chart gradient
``F(delta, theta) = d/d delta f(x* ⊞ delta, theta)`` vanishes at ``delta = 0``. By the implicit
function theorem ``d delta / d theta = -H^-1 dF/d theta`` with ``H`` the *exact* Hessian of
``f`` in that chart, and the solution is ``x*(theta) ⊞ delta(theta)``.
:func:`solve_differentiable` returns exactly that: the solver's answer (a constant for autodiff)
retracted by a ``delta`` that is zero in value and whose reverse-mode rule is
``jaxopt.implicit_diff.root_vjp`` with ``F``; its linear solve factors the exact Hessian
assembled blockwise (:func:`~uavcal_jax.vio.normal.normal_equations` with ``exact=True``)
through the same Schur complement as the solver. The Gauss-Newton matrix would leave out the
residual curvature and bias the gradient by up to ~1 %.

So ``jax.grad`` of a trajectory loss of the solution, or of the converged cost (whose
gradient is then the partial derivative, the envelope theorem), with respect to
:class:`~uavcal_jax.vio.window.CalibParams` works with any
:class:`~uavcal_jax.vio.solver.Solver`. Reverse mode only; the solve must have converged
(the rule assumes ``F = 0``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxopt.implicit_diff import root_vjp

from uavcal_jax.vio.normal import normal_equations, solve_linear
from uavcal_jax.vio.residuals import tangent_cost
from uavcal_jax.vio.solver import SolveInfo, Solver
from uavcal_jax.vio.window import FRAME_DIM, CalibParams, WindowProblem, WindowState, retract

__all__ = ["optimality", "solve_differentiable"]


def optimality(delta, state: WindowState, problem: WindowProblem, params: CalibParams):
    """``F(delta) = (d f / d delta_frames (N, 15), d f / d delta_inv_depth (L,))`` at
    ``state ⊞ delta``; zero at ``delta = 0`` when ``state`` is a minimum."""
    return jax.grad(tangent_cost, argnums=(0, 1))(delta[0], delta[1], state, problem, params)


def _zeros(state: WindowState):
    N = state.frames.position.shape[0]
    dtype = state.frames.position.dtype
    return (jnp.zeros((N, FRAME_DIM), dtype), jnp.zeros_like(state.inv_depth))


@jax.custom_vjp
def _implicit_delta(x_star, problem, params):
    return _zeros(x_star)


def _fwd(x_star, problem, params):
    return _zeros(x_star), (x_star, problem, params)


def _bwd(res, cotangent):
    return _implicit_vjp(*res, cotangent)


def _zero_cotangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


@jax.jit
def _implicit_vjp(x_star, problem, params, cotangent):
    neq = normal_equations(x_star, problem, params, exact=True)

    def solve(matvec, b):
        # H is symmetric, so the transposed system root_vjp asks for is H itself
        del matvec
        x_f, x_l = solve_linear(neq, b[0].reshape(-1), b[1], cholesky=False)
        return (x_f.reshape(b[0].shape), x_l)

    def fun(delta, params):
        return optimality(delta, x_star, problem, params)

    (d_params,) = root_vjp(fun, _zeros(x_star), (params,), cotangent, solve)
    zero = functools.partial(jax.tree_util.tree_map, _zero_cotangent)
    return zero(x_star), zero(problem), d_params


_implicit_delta.defvjp(_fwd, _bwd)


def solve_differentiable(solver: Solver, state: WindowState, problem: WindowProblem,
                         params: CalibParams) -> tuple[WindowState, SolveInfo]:
    """``solver(state, problem, params)`` with implicit gradients with respect to ``params``.

    ``problem`` (measurements) is held constant: its cotangent is zero. Call the returned
    function's gradient outside ``jax.jit`` to reuse the solver's and the backward rule's own
    compiled executables (inside an outer ``jit`` both are compiled again as part of it).
    """
    stop = jax.lax.stop_gradient
    x_star, info = solver(stop(state), stop(problem), stop(params))
    x_star = stop(x_star)
    d_f, d_l = _implicit_delta(x_star, problem, params)
    return retract(x_star, d_f, d_l), info
