"""The structured window solve against jaxopt, dense normal equations and the ground truth."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from vio_dense import stacked_residuals

from uavcal_jax.vio import (
    CostConfig,
    JaxoptSolver,
    SolverConfig,
    StructuredSolver,
    frame_difference,
    normal_equations,
    retract,
    robust,
)
from uavcal_jax.vio.normal import solve_linear, solve_step
from uavcal_jax.vio.synthetic import SyntheticConfig, perturb, synthetic_window

PIXEL_SIGMA = 0.5
# the reprojection residual carries the noise of both the observation and the anchor bearing
COST = CostConfig(pixel_sigma=PIXEL_SIGMA * np.sqrt(2.0))
SOLVER = StructuredSolver(SolverConfig(max_iterations=40, ftol=0.0))


@pytest.fixture(scope="module")
def solved():
    with jax.enable_x64(True):
        w = synthetic_window(SyntheticConfig(n_frames=5, n_landmarks=60,
                                             pixel_sigma=PIXEL_SIGMA), seed=0, cost_config=COST)
        x0 = perturb(w.truth, seed=1)
        x, info = SOLVER(x0, w.problem, w.params)
        yield w, x0, x, info


def _flat(state):
    f = state.frames
    return np.concatenate([np.asarray(a).reshape(-1) for a in
                           (f.rotation, f.position, f.velocity, f.bias_gyro, f.bias_accel,
                            state.inv_depth)])


def test_structured_matches_jaxopt_levenberg_marquardt(solved, x64):
    w, x0, x, info = solved
    assert float(info.cost_final) < 1e-4 * float(info.cost_initial)
    ref, ref_info = JaxoptSolver("levenberg_marquardt", maxiter=50, tol=1e-10)(
        x0, w.problem, w.params)
    np.testing.assert_allclose(float(info.cost_final), float(ref_info.cost_final), rtol=1e-10)
    np.testing.assert_allclose(_flat(x), _flat(ref), rtol=0, atol=1e-6)


def test_solution_within_noise_of_truth(solved, x64):
    w, _, x, _ = solved
    neq = normal_equations(x, w.problem, w.params)
    e_f = frame_difference(x.frames, w.truth.frames).reshape(-1)
    e_l = np.asarray(x.inv_depth - w.truth.inv_depth)
    # Mahalanobis norm of the error under the solve's own information matrix: chi^2 with
    # 75 + 60 degrees of freedom if the model were exact. It is not quite: like VINS-Fusion the
    # cost takes the anchor bearing as exact, while it carries pixel noise too (correlated
    # across a landmark's residuals, so the sqrt(2) sigma inflation does not capture it) --
    # hence a bound of 3 dof (the noise-free IMU makes it smaller). A wrong solve is orders of
    # magnitude above it: the warm start is at about 1e7.
    m2 = float(e_f @ neq.H_ff @ e_f + 2 * e_f @ neq.H_fl @ e_l + np.sum(neq.H_ll * e_l**2))
    dof = e_f.size + e_l.size
    assert m2 < 3 * dof
    # the gauge is fixed by the prior on keyframe 0 (5 mm, 2 mrad): errors at that level
    assert float(jnp.max(jnp.abs(x.frames.position - w.truth.frames.position))) < 0.03
    assert float(jnp.max(jnp.abs(e_f.reshape(-1, 15)[:, :3]))) < 0.01


def test_schur_normal_equations_equal_dense(solved, x64):
    w, x0, _, _ = solved
    N, L, M = w.problem.capacities
    # exercise the masks: drop the last keyframe, one landmark and one observation
    problem = dataclasses.replace(
        w.problem,
        frame_mask=w.problem.frame_mask.at[N - 1].set(False),
        landmarks=dataclasses.replace(w.problem.landmarks,
                                      mask=w.problem.landmarks.mask.at[3].set(False)),
        observations=dataclasses.replace(w.problem.observations,
                                         mask=w.problem.observations.mask.at[0].set(False)))
    neq = normal_equations(x0, problem, w.params)

    def res(z):
        return stacked_residuals(retract(x0, z[:15 * N].reshape(N, 15), z[15 * N:]),
                                 problem, w.params)[0]

    z0 = jnp.zeros(15 * N + L)
    J = jax.jit(jax.jacfwd(res))(z0)
    r, wt = jax.jit(stacked_residuals)(x0, problem, w.params)
    H = J.T @ (wt[:, None] * J)
    g = J.T @ (wt * r)
    nf = 15 * N
    fa, la = np.asarray(neq.frame_active), np.asarray(neq.landmark_active)
    assert not fa[-15:].any() and not la[3]

    def close(a, b):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                   atol=1e-9 * float(jnp.max(jnp.abs(b))))

    close(neq.H_ff - jnp.diag(jnp.where(neq.frame_active, 0.0, 1.0)), H[:nf, :nf])
    close(neq.H_fl, H[:nf, nf:])
    close(jnp.where(neq.landmark_active, neq.H_ll, 0.0), jnp.diag(H[nf:, nf:]))
    assert float(jnp.max(jnp.abs(H[nf:, nf:] - jnp.diag(jnp.diag(H[nf:, nf:]))))) == 0.0
    close(neq.g_f, g[:nf])
    close(neq.g_l, g[nf:])
    # the Schur-complement step solves the full system on the active variables
    act = np.concatenate([fa, la])
    Ha = H[np.ix_(act, act)]
    s = 1.0 / jnp.sqrt(jnp.diag(Ha))
    dense = -s * jnp.linalg.solve(s[:, None] * Ha * s[None, :], s * g[act])
    dx_f, dx_l = solve_step(neq)
    step = jnp.concatenate([dx_f.reshape(-1), dx_l])
    np.testing.assert_allclose(np.asarray(step[act]), np.asarray(dense), rtol=1e-6,
                               atol=1e-9 * float(jnp.max(jnp.abs(dense))))
    assert float(jnp.max(jnp.abs(step[~act]))) == 0.0
    # and the damped system is the undamped one plus lambda diag(H)
    lam = 1e-3
    x_f, x_l = solve_linear(neq, -neq.g_f, -neq.g_l, lam)
    Hd = H + lam * jnp.diag(jnp.clip(jnp.diag(H), 1e-6, None))
    damped = jnp.linalg.solve((s[:, None] * Hd[np.ix_(act, act)] * s[None, :]), s * -g[act]) * s
    np.testing.assert_allclose(np.asarray(jnp.concatenate([x_f, x_l])[act]), np.asarray(damped),
                               rtol=1e-6, atol=1e-9 * float(jnp.max(jnp.abs(damped))))


def test_huber_bounds_a_gross_outlier(solved, x64):
    w, _, x, _ = solved
    obs = w.problem.observations
    # a temporal observation in the newest keyframe, left camera
    m = int(np.flatnonzero(np.asarray((obs.frame == 4) & (obs.camera == 0) & obs.mask))[0])
    fx = w.problem.config.focal_px

    def solve_with(shift_px, keep=True):
        o = dataclasses.replace(obs, xy=obs.xy.at[m, 0].add(shift_px / fx),
                                mask=obs.mask.at[m].set(keep))
        return SOLVER(x, dataclasses.replace(w.problem, observations=o), w.params)[0]

    without = _flat(solve_with(0.0, keep=False))
    influence = {px: np.abs(_flat(solve_with(px)) - without).max() for px in (20.0, 200.0)}
    # quadratic cost: the pull grows with the error (x10); Huber: it saturates
    assert influence[200.0] < 1.5 * influence[20.0]
    # and its IRLS weight at 200 px is about sigma / error
    s = (200.0 / COST.pixel_sigma) ** 2
    assert float(robust.weight(jnp.asarray(s), "huber")) < 0.01


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "none"])
def test_robust_weight_is_derivative(kernel, x64):
    s = jnp.array([0.0, 0.3, 1.0, 2.0, 50.0, 1e4])
    dr = jax.vmap(jax.grad(lambda t: robust.rho(t, kernel, 1.5)))(s + 1e-9)
    np.testing.assert_allclose(np.asarray(robust.weight(s + 1e-9, kernel, 1.5)),
                               np.asarray(dr), rtol=1e-12)
    eq = robust.equivalent_scale(s, kernel, 1.5)
    np.testing.assert_allclose(np.asarray(eq**2 * s), np.asarray(robust.rho(s, kernel, 1.5)),
                               rtol=1e-12, atol=1e-300)


def test_analytic_observation_jacobian_equals_autodiff(solved, x64):
    from uavcal_jax.vio.residuals import (
        gather_observations,
        observation_jacobian,
        observation_local,
    )
    w, x0, _, _ = solved
    g = gather_observations(x0, w.problem, w.params)
    # one point pushed behind the observing camera: its clamped depth has zero derivative
    g = dict(g, inv_depth=g["inv_depth"].at[0].set(-g["inv_depth"][0]))
    cfg = w.problem.config
    r, J = observation_jacobian(g, cfg)

    def local(gi):
        return jax.jacfwd(lambda d: observation_local(gi, d[:6], d[6:12], d[12], cfg))(
            jnp.zeros(13))

    J_ad = jax.vmap(local)(g)
    r_ad = jax.vmap(lambda gi: observation_local(gi, jnp.zeros(6), jnp.zeros(6), 0.0, cfg))(g)
    np.testing.assert_allclose(np.asarray(r), np.asarray(r_ad), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.asarray(J), np.asarray(J_ad), rtol=1e-9,
                               atol=1e-9 * float(jnp.max(jnp.abs(J_ad))))
