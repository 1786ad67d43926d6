"""The window solve behind one small interface, and the structured Levenberg-Marquardt.

A :class:`Solver` is any callable ``solver(state, problem, params) -> (state, SolveInfo)``
that minimises :func:`~uavcal_jax.vio.residuals.window_cost` over the keyframes and inverse
depths from the warm start ``state``. Two implementations:

* :class:`StructuredSolver` (production): Levenberg-Marquardt on the structured normal
  equations of :mod:`uavcal_jax.vio.normal` -- landmarks eliminated by Schur complement,
  Cholesky on the 15N frame block -- in a ``lax.while_loop``; a step is kept only when it
  lowers the cost (the normal equations are then rebuilt there), the damping falls after a
  kept step and rises after a rejected one.
* :class:`~uavcal_jax.vio.reference.JaxoptSolver`: ``jaxopt.GaussNewton`` /
  ``LevenbergMarquardt`` on the flattened residual vector (the reference in tests).

:func:`~uavcal_jax.vio.implicit.solve_differentiable` wraps either with implicit
differentiation, so a maintained alternative (optimistix) only has to satisfy the protocol.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Protocol

import jax
import jax.numpy as jnp

from uavcal_jax.vio.config import SolverConfig
from uavcal_jax.vio.normal import normal_equations, solve_step
from uavcal_jax.vio.residuals import window_cost
from uavcal_jax.vio.window import CalibParams, WindowProblem, WindowState, retract

__all__ = ["SolveInfo", "Solver", "StructuredSolver", "gauss_newton_step", "structured_solve"]


@dataclasses.dataclass(frozen=True)
class SolveInfo:
    """What a solve did (a pytree of scalars).

    Attributes:
        iterations: () int32 iterations run (accepted or not).
        cost_initial, cost_final: () the cost at the warm start and at the result.
        converged: () bool, a stopping test (not the iteration limit) ended the solve.
    """

    iterations: jax.Array
    cost_initial: jax.Array
    cost_final: jax.Array
    converged: jax.Array


jax.tree_util.register_dataclass(
    SolveInfo, data_fields=[f.name for f in dataclasses.fields(SolveInfo)], meta_fields=[])


class Solver(Protocol):
    """``solver(state, problem, params) -> (state, SolveInfo)``: minimise the window cost."""

    def __call__(self, state: WindowState, problem: WindowProblem, params: CalibParams
                 ) -> tuple[WindowState, SolveInfo]: ...


def gauss_newton_step(state: WindowState, problem: WindowProblem, params: CalibParams,
                      damping=0.0) -> tuple[WindowState, jax.Array]:
    """One structured (damped) Gauss-Newton iteration: assemble, eliminate the landmarks,
    factor, back-substitute, retract. Returns the new state and its cost (the step is not
    checked; :func:`structured_solve` does that)."""
    neq = normal_equations(state, problem, params)
    dx_f, dx_l = solve_step(neq, damping)
    new = retract(state, dx_f, dx_l)
    return new, window_cost(new, problem, params)


@functools.partial(jax.jit, static_argnames=("config",))
def structured_solve(state: WindowState, problem: WindowProblem, params: CalibParams,
                     config: SolverConfig | None = None) -> tuple[WindowState, SolveInfo]:
    """Structured Levenberg-Marquardt from the warm start ``state`` (see the module docstring;
    ``config`` defaults to :class:`~uavcal_jax.vio.config.SolverConfig`)."""
    config = SolverConfig() if config is None else config
    cost0 = window_cost(state, problem, params)

    def cond(carry):
        it, done = carry[3], carry[4]
        return (it < config.max_iterations) & ~done

    def body(carry):
        # the normal equations are rebuilt every iteration (also after a rejected step) so
        # that the loop traces them once: compile time, not run time, is the scarce resource
        x, cost, lam, it, _ = carry
        dx_f, dx_l = solve_step(normal_equations(x, problem, params), lam)
        cand = retract(x, dx_f, dx_l)
        c_new = window_cost(cand, problem, params)
        ok = jnp.isfinite(c_new) & (c_new < cost)
        x = jax.tree_util.tree_map(lambda n, o: jnp.where(ok, n, o), cand, x)
        rel = (cost - c_new) / jnp.maximum(cost, jnp.finfo(c_new.dtype).tiny)
        small = ok & (rel < config.ftol)
        stuck = ~ok & ((lam == 0.0) | (lam * config.damping_factor > config.max_damping))
        cost = jnp.where(ok, c_new, cost)
        lam = jnp.where(ok, jnp.maximum(lam / config.damping_factor, config.min_damping),
                        lam * config.damping_factor)
        lam = jnp.where(config.initial_damping == 0.0, 0.0, lam)
        return x, cost, lam, it + 1, small | stuck

    init = (state, cost0, jnp.asarray(config.initial_damping, cost0.dtype),
            jnp.asarray(0, jnp.int32), jnp.asarray(False))
    x, cost, _, it, done = jax.lax.while_loop(cond, body, init)
    return x, SolveInfo(it, cost0, cost, done)


@dataclasses.dataclass(frozen=True)
class StructuredSolver:
    """:class:`Solver` running :func:`structured_solve` with ``config``."""

    config: SolverConfig = SolverConfig()

    def __call__(self, state: WindowState, problem: WindowProblem, params: CalibParams
                 ) -> tuple[WindowState, SolveInfo]:
        return structured_solve(state, problem, params, self.config)
