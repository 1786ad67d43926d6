"""Implicit gradients of the window solution w.r.t. the IMU offset against finite differences
of re-solved windows."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.vio import (
    CostConfig,
    SolverConfig,
    StructuredSolver,
    gauss_newton_step,
    solve_differentiable,
    window_cost,
)
from uavcal_jax.vio.synthetic import SyntheticConfig, perturb, synthetic_window

# the same window and solver as tests/test_vio_solver.py, so the compiled solve is shared
COST = CostConfig(pixel_sigma=0.5 * np.sqrt(2.0))
SOLVER = StructuredSolver(SolverConfig(max_iterations=40, ftol=0.0))


@pytest.fixture(scope="module")
def window():
    with jax.enable_x64(True):
        w = synthetic_window(SyntheticConfig(n_frames=5, n_landmarks=60, pixel_sigma=0.5),
                             seed=0, cost_config=COST)
        x, _ = SOLVER(perturb(w.truth, seed=1), w.problem, w.params)
        yield w, x


@pytest.mark.heavy
def test_implicit_gradient_matches_finite_differences(window, x64):
    w, x = window

    def solve(offset):
        params = dataclasses.replace(w.params, imu_offset=offset)
        return solve_differentiable(SOLVER, x, w.problem, params)[0], params

    def trajectory_loss(offset):
        xs, _ = solve(offset)
        return (jnp.sum((xs.frames.position - w.truth.frames.position) ** 2)
                + jnp.sum(xs.frames.velocity[-1] ** 2))

    def converged_cost(offset):
        xs, params = solve(offset)
        return window_cost(xs, w.problem, params)

    def both(offset):
        # the solver stops when no step lowers the cost, which pins the solution only to about
        # sqrt(eps) of it; undamped Gauss-Newton steps, taken whatever the cost does, converge
        # to the stationary point itself, so the differences resolve the gradient
        params = dataclasses.replace(w.params, imu_offset=offset)
        xs, _ = SOLVER(x, w.problem, params)
        for _ in range(4):
            xs, _ = gn_step(xs, w.problem, params)
        return np.array([trajectory_loss_of(xs), float(window_cost(xs, w.problem, params))])

    def trajectory_loss_of(xs):
        return float(jnp.sum((xs.frames.position - w.truth.frames.position) ** 2)
                     + jnp.sum(xs.frames.velocity[-1] ** 2))

    o = w.params.imu_offset
    # outside jit, so the compiled solve and backward rule are reused across calls
    g_loss = np.asarray(jax.grad(trajectory_loss)(o))
    g_cost = np.asarray(jax.grad(converged_cost)(o))
    # central differences at h and h/2, Richardson-extrapolated (the h^2 term cancels)
    gn_step = jax.jit(gauss_newton_step)
    h = 2e-5
    fd = np.zeros((6, 2))
    for i in range(6):
        e = jnp.zeros(6).at[i].set(h)
        d1 = (both(o + e) - both(o - e)) / (2 * h)
        d2 = (both(o + e / 2) - both(o - e / 2)) / h
        fd[i] = (4 * d2 - d1) / 3
    assert np.all(np.abs(g_loss) > 1e-3)  # every channel moves the solution
    # agreement at the 1e-4 level (the re-solves' own precision limits the differences); a
    # Gauss-Newton Hessian in the implicit rule would be off by about 1e-2
    np.testing.assert_allclose(g_loss, fd[:, 0], rtol=3e-4, atol=1e-7)
    np.testing.assert_allclose(g_cost, fd[:, 1], rtol=1e-4, atol=1e-6 * np.abs(fd[:, 1]).max())
