"""Marginalisation of the oldest keyframe (against a dense Schur complement of the jacfwd
Hessian, the full problem's Gauss-Newton step, solution and covariance, the gauge) and the drop
of the second-newest frame (against direct preintegration and the ground truth)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from vio_dense import stacked_residuals

from uavcal_jax.imu import EUROC_ADIS16448, preintegrate
from uavcal_jax.vio import (
    CostConfig,
    ImuSamples,
    SolverConfig,
    StructuredSolver,
    drop_second_newest,
    frame_difference,
    marginal_information,
    marginalize_oldest,
    normal_equations,
    retract,
    slide_imu_samples,
)
from uavcal_jax.vio.normal import solve_step
from uavcal_jax.vio.residuals import prior_residual
from uavcal_jax.vio.synthetic import SyntheticConfig, imu_samples, perturb, synthetic_window
from uavcal_jax.vio.window import retract_frames

# the window and solver of tests/test_vio_solver.py, so compiled solves are shared
SYN = SyntheticConfig(n_frames=5, n_landmarks=60, pixel_sigma=0.5)
COST = CostConfig(pixel_sigma=0.5 * np.sqrt(2.0))
SOLVER = StructuredSolver(SolverConfig(max_iterations=40, ftol=0.0))
D = 15


@pytest.fixture(scope="module")
def solved():
    with jax.enable_x64(True):
        w = synthetic_window(SYN, seed=0, cost_config=COST)
        x, _ = SOLVER(perturb(w.truth, seed=1), w.problem, w.params)
        # a linearisation point off the optimum, as after a few iterations of a real solve
        x_lin = perturb(x, seed=2, rotation=1e-3, position=5e-3, velocity=5e-3,
                        bias_gyro=1e-4, bias_accel=1e-3, inv_depth=0.02)
        yield w, x, x_lin


def _residual(z, state, problem, params):
    N = problem.capacities[0]
    return stacked_residuals(retract(state, z[:D * N].reshape(N, D), z[D * N:]),
                             problem, params)[0]


_jacobian = jax.jit(jax.jacfwd(_residual))


def _dense(state, problem, params, obs_keep=None, imu_keep=None):
    """Gauss-Newton ``(H, g)`` over (15N frame tangents, L inverse depths) from jacfwd of the
    flattened residual, optionally restricted to some factors (by masks)."""
    if obs_keep is not None:
        problem = dataclasses.replace(
            problem,
            observations=dataclasses.replace(problem.observations,
                                             mask=problem.observations.mask & obs_keep),
            imu=dataclasses.replace(problem.imu, mask=problem.imu.mask & imu_keep))
    N = problem.capacities[0]
    J = _jacobian(jnp.zeros(D * N + state.inv_depth.shape[0]), state, problem, params)
    r, wt = stacked_residuals(state, problem, params)
    return np.asarray(J.T @ (wt[:, None] * J)), np.asarray(J.T @ (wt * r))


def _eliminated(w):
    """Landmarks anchored in keyframe 0 or observed by it, from the numpy arrays."""
    obs, lm = w.problem.observations, w.problem.landmarks
    anchor, o_f, o_l = (np.asarray(a) for a in (lm.anchor, obs.frame, obs.landmark))
    o_m = np.asarray(obs.mask)
    elim = (anchor == 0) & np.asarray(lm.mask)
    elim[o_l[o_m & (o_f == 0)]] = True
    return elim


def _schur(H, g, keep, drop):
    """Dense Schur complement onto ``keep``; the eliminated block's directions without
    information (all-zero rows) are left out of its inverse."""
    live = drop[np.any(H[drop] != 0, axis=1)]
    Hk = H[np.ix_(keep, keep)] - H[np.ix_(keep, live)] @ np.linalg.solve(
        H[np.ix_(live, live)], H[np.ix_(live, keep)])
    gk = g[keep] - H[np.ix_(keep, live)] @ np.linalg.solve(H[np.ix_(live, live)], g[live])
    return Hk, gk


def _part(frames, index):
    return jax.tree_util.tree_map(lambda a: a[index], frames)


def _scaled_close(a, b, scale, tol):
    """``|s (a - b) s|`` below ``tol`` with ``s = scale^-1/2`` (scale-free; 1 where a variable
    has no information, whose entries must then vanish outright)."""
    s = 1.0 / np.sqrt(np.where(scale > 0, scale, 1.0))
    err = (s[:, None] * (a - b) * s[None, :]) if a.ndim == 2 else s * (a - b)
    assert np.max(np.abs(err)) < tol, np.max(np.abs(err))


def test_prior_is_dense_schur_complement_and_gn_step_matches(solved, x64):
    w, _, x = solved
    N, L, _ = w.problem.capacities
    elim = _eliminated(w)
    assert 0 < elim.sum() < L
    obs_keep = jnp.asarray(elim[np.asarray(w.problem.observations.landmark)])
    H, g = _dense(x, w.problem, w.params, obs_keep, jnp.arange(N - 1) == 0)
    lm_idx = D * N + np.flatnonzero(elim)
    drop = np.concatenate([np.arange(D), lm_idx])
    keep = np.arange(D, D * N)
    Hk, gk = _schur(H, g, keep, drop)

    x2, p2 = marginalize_oldest(x, w.problem, w.params)
    Jp, rp = np.asarray(p2.prior.J), np.asarray(p2.prior.r)
    n = D * (N - 1)
    _scaled_close(Jp.T @ Jp, np.pad(Hk, ((0, D), (0, D))), np.pad(np.diag(Hk), (0, D),
                                                                 constant_values=1.0), 1e-9)
    _scaled_close((Jp.T @ rp)[:n], gk, np.diag(Hk), 1e-9)
    assert np.all(Jp[:, n:] == 0)
    # the same matrices from the unshifted information
    Hm, bm = marginal_information(x, w.problem, w.params)
    _scaled_close(np.asarray(Hm)[D:, D:], Hk, np.diag(Hk), 1e-9)

    # one Gauss-Newton step: reduced problem (remaining factors + prior) vs full problem
    dx_f, dx_l = solve_step(normal_equations(x, w.problem, w.params))
    dy_f, dy_l = solve_step(normal_equations(x2, p2, w.params))
    Hfull, _ = _dense(x, w.problem, w.params)
    scale = np.sqrt(np.diag(Hfull))
    full = np.concatenate([np.asarray(dx_f).reshape(-1), np.asarray(dx_l)]) * scale
    surv = ~elim & np.asarray(w.problem.landmarks.mask)
    sel = np.concatenate([np.arange(D, D * N), D * N + np.flatnonzero(surv)])
    red = np.concatenate([np.asarray(dy_f)[:N - 1].reshape(-1),
                          np.asarray(dy_l)[surv]]) * scale[sel]
    assert np.max(np.abs(full)) > 1.0  # the step is not trivially small (in sigmas)
    np.testing.assert_allclose(red, full[sel], rtol=0, atol=1e-8 * np.max(np.abs(full)))
    assert float(jnp.max(jnp.abs(dy_f[N - 1]))) == 0.0


def test_resolve_after_marginalisation_matches_full_solve(solved, x64):
    w, x, _ = solved
    N = w.problem.capacities[0]
    x2, p2 = marginalize_oldest(x, w.problem, w.params)
    start = perturb(x2, seed=3, rotation=2e-3, position=1e-2, velocity=1e-2, bias_gyro=1e-4,
                    bias_accel=1e-3, inv_depth=0.05)
    y, _ = SOLVER(start, p2, w.params)
    # Tolerance: the prior is the second-order expansion of the marginalised factors at x, so
    # at x the reduced gradient equals the full gradient on the surviving variables, which is
    # zero at the full optimum x. The prior's linearisation error (the dropped O(|dx|^2)
    # terms of the eliminated factors) changes the reduced cost's curvature away from x but
    # not its stationary point: the re-solve must return x up to its own convergence. We ask
    # for 1e-4 sigma per component (sigmas: the full solve's diagonal information), far below
    # the 1-sigma statistical error and far above the ~1e-8 sigma a 40-iteration solve reaches.
    Hfull, _ = _dense(x, w.problem, w.params)
    s = np.sqrt(np.diag(Hfull))
    e_f = np.asarray(frame_difference(_part(y.frames, slice(0, N - 1)),
                                      _part(x.frames, slice(1, N))))
    assert np.max(np.abs(e_f.reshape(-1) * s[D:D * N])) < 1e-4
    surv = np.asarray(p2.landmarks.mask)
    e_l = np.asarray(y.inv_depth - x.inv_depth)[surv] * s[D * N:][surv]
    assert np.max(np.abs(e_l)) < 1e-4
    # the warm start was many sigmas away
    e0 = np.asarray(frame_difference(_part(start.frames, slice(0, N - 1)),
                                     _part(x2.frames, slice(0, N - 1))))
    assert np.max(np.abs(e0.reshape(-1) * s[D:D * N])) > 10.0


def test_prior_keeps_first_estimate_jacobian(solved, x64):
    w, _, x = solved
    N = w.problem.capacities[0]
    x2, p2 = marginalize_oldest(x, w.problem, w.params)
    prior = p2.prior
    # the linearisation point is the estimate at marginalisation time
    np.testing.assert_array_equal(np.asarray(prior.lin.position), np.asarray(x2.frames.position))
    lin = prior.lin

    def r_of(d):
        return prior_residual(retract_frames(lin, d.reshape(N, D)), p2)

    d0 = jnp.zeros(N * D)
    rng = np.random.default_rng(4)
    d1 = jnp.asarray(np.repeat([3e-2, 0.1, 0.1, 1e-3, 1e-2], 3)[None] * rng.standard_normal(
        (N, D))).reshape(-1)
    J0, J1 = jax.jacfwd(r_of)(d0), jax.jacfwd(r_of)(d1)
    mask = np.repeat(np.asarray(p2.frame_mask), D)
    Jp = np.asarray(prior.J) * mask[None, :]
    tol = 1e-12 * np.max(np.abs(Jp))
    # the same Jacobian at two states far apart: the prior is never re-linearised
    np.testing.assert_allclose(np.asarray(J0), Jp, rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(J1), Jp, rtol=0, atol=tol)
    # and affine in the tangent difference from the fixed point
    r1 = np.asarray(r_of(d1))
    np.testing.assert_allclose(r1, np.asarray(prior.r) + Jp @ np.asarray(d1), rtol=0,
                               atol=1e-10 * np.max(np.abs(r1)))
    # a second marginalisation keeps its own (new) point, not the moved estimate
    y = perturb(x2, seed=5)
    _, p3 = marginalize_oldest(y, p2, w.params)
    np.testing.assert_array_equal(np.asarray(p3.prior.lin.position[:N - 2]),
                                  np.asarray(y.frames.position[1:N - 1]))


def _gauge(frames, N):
    """(15N, 4) tangent directions of a global yaw about world z and of a global translation."""
    R, p, v = (np.asarray(a) for a in (frames.rotation, frames.position, frames.velocity))
    ez = np.array([0.0, 0.0, 1.0])
    G = np.zeros((N, D, 4))
    G[:, 0:3, 0] = np.einsum("nji,j->ni", R, ez)  # right perturbation R^T e_z
    G[:, 3:6, 0] = np.cross(ez, p)
    G[:, 6:9, 0] = np.cross(ez, v)
    G[:, 3:6, 1:] = np.eye(3)
    return G.reshape(N * D, 4)


def test_marginal_covariance_and_gauge(solved, x64):
    w, x, _ = solved
    N = w.problem.capacities[0]
    x2, p2 = marginalize_oldest(x, w.problem, w.params)
    # the synthetic window fixes the gauge with a prior on keyframe 0: the surviving frames'
    # marginal covariance must be that of the full problem
    Hf, _ = _dense(x, w.problem, w.params)
    Hr, _ = _dense(x2, p2, w.params)
    act_f = np.diag(Hf) > 0
    act_r = np.diag(Hr) > 0
    Cf = np.zeros_like(Hf)
    Cf[np.ix_(act_f, act_f)] = np.linalg.inv(Hf[np.ix_(act_f, act_f)])
    Cr = np.zeros_like(Hr)
    Cr[np.ix_(act_r, act_r)] = np.linalg.inv(Hr[np.ix_(act_r, act_r)])
    A = Cf[D:D * N, D:D * N]
    B = Cr[:D * (N - 1), :D * (N - 1)]
    s = 1.0 / np.sqrt(np.diag(A))
    np.testing.assert_allclose(s[:, None] * B * s[None, :], s[:, None] * A * s[None, :],
                               rtol=0, atol=1e-8)

    # without the gauge prior the factors leave yaw and translation free: the marginal
    # information, and the prior made from it, must not constrain them
    free = dataclasses.replace(w.problem, prior=dataclasses.replace(
        w.problem.prior, mask=jnp.asarray(False)))
    Hm, _ = marginal_information(x, free, w.params)
    Hm = np.asarray(Hm)
    G = _gauge(x.frames, N)
    G[:D] = 0.0
    dg = np.diag(Hm)

    def rayleigh(H, v):
        return float(v @ H @ v) / float(v @ (dg * v))

    rng = np.random.default_rng(6)
    other = rng.standard_normal(D * N) / np.sqrt(np.maximum(dg, 1e-300))
    other[:D] = 0.0
    assert rayleigh(Hm, other) > 1e-3
    for c in range(4):
        assert abs(rayleigh(Hm, G[:, c])) < 1e-9
    _, pf = marginalize_oldest(x, free, w.params)
    Jp = np.asarray(pf.prior.J)
    Hp = Jp.T @ Jp
    Gs = _gauge(x2.frames, N)
    Gs[D * (N - 1):] = 0.0
    dg = np.diag(Hp)
    other = np.roll(other, -D)
    assert rayleigh(Hp, other) > 1e-3
    for c in range(4):
        assert abs(rayleigh(Hp, Gs[:, c])) < 1e-9


def _window_samples():
    """The synthetic window's raw IMU samples, padded to twice their count per interval."""
    dt, gyro, accel = imu_samples(SYN)
    S = 2 * dt.shape[1]
    pad = ((0, 0), (0, S - dt.shape[1]))
    samples = ImuSamples(jnp.asarray(np.pad(dt, pad, constant_values=1.0)),
                         jnp.asarray(np.pad(gyro, pad + ((0, 0),))),
                         jnp.asarray(np.pad(accel, pad + ((0, 0),))),
                         jnp.asarray(np.pad(np.ones(dt.shape, bool), pad)))
    return dt, gyro, accel, samples


def test_drop_after_marginalisation_marginalises_the_prior(solved, x64):
    w, x, _ = solved
    N = w.problem.capacities[0]
    x2, p2 = marginalize_oldest(x, w.problem, w.params)
    # slots 0 .. N - 2 in use and all in the prior; drop slot N - 3, the newest moves down
    _, p3, _ = drop_second_newest(x2, p2, slide_imu_samples(_window_samples()[3]),
                                  EUROC_ADIS16448, w.params)
    J, r = np.asarray(p2.prior.J), np.asarray(p2.prior.r)
    H, g = J.T @ J, J.T @ r
    k, n = N - 3, N - 2
    blk = np.arange(N * D) // D
    drop = np.flatnonzero(blk == k)
    keep = np.concatenate([np.flatnonzero(blk < k), np.flatnonzero(blk == n)])
    Hk, gk = _schur(H, g, keep, drop)
    J3, r3 = np.asarray(p3.prior.J), np.asarray(p3.prior.r)
    m = keep.size
    _scaled_close((J3.T @ J3)[:m, :m], Hk, np.diag(Hk), 1e-9)
    _scaled_close((J3.T @ r3)[:m], gk, np.diag(Hk), 1e-9)
    assert np.all(J3[:, m:] == 0)
    np.testing.assert_array_equal(np.asarray(p3.prior.lin.position[k]),
                                  np.asarray(p2.prior.lin.position[n]))


def test_drop_second_newest(solved, x64):
    # tracks from two keyframes on, so that landmarks are anchored in the dropped frame; the
    # capacities of the shared window, so that its compiled solve is reused
    M = solved[0].problem.capacities[2]
    w = synthetic_window(dataclasses.replace(SYN, track_length=(2, 10), obs_capacity=M),
                         seed=0, cost_config=COST)
    N, L, _ = w.problem.capacities
    x, _ = SOLVER(perturb(w.truth, seed=1), w.problem, w.params)
    dt, gyro, accel, samples = _window_samples()
    # the window's intervals are the preintegrated samples
    np.testing.assert_allclose(np.asarray(preintegrate(samples.dt, samples.gyro, samples.accel,
                                                       mask=samples.mask).delta_p),
                               np.asarray(w.problem.imu.pim.delta_p), rtol=0, atol=1e-15)
    x2, p2, s2 = drop_second_newest(x, w.problem, samples, EUROC_ADIS16448, w.params)
    k = N - 2
    ref = preintegrate(np.concatenate([dt[k - 1], dt[k]]), np.concatenate([gyro[k - 1], gyro[k]]),
                       np.concatenate([accel[k - 1], accel[k]]))
    got = jax.tree_util.tree_map(lambda a: a[k - 1], p2.imu.pim)
    for name in ("delta_R", "delta_v", "delta_p", "delta_t", "theta", "d_R_d_bg", "d_v_d_bg",
                 "d_v_d_ba", "d_p_d_bg", "d_p_d_ba", "cov", "cov_bias"):
        a, b = np.asarray(getattr(got, name)), np.asarray(getattr(ref, name))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.max(np.abs(b)), err_msg=name)
    assert bool(got.valid) and int(got.n_samples) == 2 * dt.shape[1]
    np.testing.assert_array_equal(np.asarray(p2.frame_mask), np.arange(N) < N - 1)
    np.testing.assert_array_equal(np.asarray(p2.imu.mask), np.arange(N - 1) < N - 2)
    assert int(s2.mask[k - 1].sum()) == 2 * dt.shape[1] and not bool(s2.mask[k:].any())
    # the newest frame moved into slot N - 2; the dropped frame's observations are gone
    np.testing.assert_array_equal(np.asarray(x2.frames.position[k]),
                                  np.asarray(x.frames.position[N - 1]))
    obs = w.problem.observations
    kept = np.asarray(p2.observations.mask)
    assert not np.any(kept & (np.asarray(obs.frame) == k))
    assert np.all(np.asarray(p2.observations.frame)[kept] <= k)
    # the solve afterwards: finite, and within noise of the truth (as the full window's is)
    y, info = SOLVER(perturb(x2, seed=7), p2, w.params)
    assert np.isfinite(float(info.cost_final))
    truth = _part(w.truth.frames, np.r_[0:k, N - 1])
    got_f = _part(y.frames, slice(0, N - 1))
    e = np.asarray(frame_difference(got_f, truth))
    assert np.max(np.abs(e[:, 3:6])) < 0.03 and np.max(np.abs(e[:, 0:3])) < 0.01
    used = np.asarray(p2.landmarks.mask) & np.isin(np.arange(L),
                                                   np.asarray(p2.observations.landmark)[kept])
    moved = np.asarray(w.problem.landmarks.anchor) == k
    rel = np.abs(np.asarray(y.inv_depth / w.truth.inv_depth) - 1.0)[used & ~moved]
    assert np.median(rel) < 0.05
    # landmarks anchored in the dropped frame now live in the newest frame's camera 0
    re = used & moved
    assert re.sum() > 0
    np.testing.assert_array_equal(np.asarray(p2.landmarks.anchor)[re], k)
    R, p = np.asarray(w.truth.frames.rotation[N - 1]), np.asarray(w.truth.frames.position[N - 1])
    R_C, t_C = np.asarray(w.params.R_BC[0]), np.asarray(w.params.t_BC[0])
    z = (((w.points[re] - p) @ R) - t_C) @ R_C
    rel = np.abs(np.asarray(y.inv_depth)[re] * z[:, 2] - 1.0)
    assert np.median(rel) < 0.05


def test_slide_imu_samples(x64):
    rng = np.random.default_rng(8)
    samples = ImuSamples(jnp.asarray(rng.uniform(1e-3, 1e-2, (4, 6))),
                         jnp.asarray(rng.standard_normal((4, 6, 3))),
                         jnp.asarray(rng.standard_normal((4, 6, 3))), jnp.ones((4, 6), bool))
    out = slide_imu_samples(samples)
    np.testing.assert_array_equal(np.asarray(out.gyro[:3]), np.asarray(samples.gyro[1:]))
    expected = np.repeat(np.arange(4) < 3, 6).reshape(4, 6)
    np.testing.assert_array_equal(np.asarray(out.mask), expected)
