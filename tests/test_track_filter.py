"""track.filter: the constant-velocity Kalman filter's process noise against the textbook
matrix, its consistency (NEES inside chi-square bounds over vmapped Monte-Carlo runs), the gate,
prediction while unseen, loss and re-initialisation."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest
from scipy.integrate import simpson
from scipy.stats import chi2
from track_folds import run_filter

from uavcal_jax.track import filter as F

DT = 0.1
#: a slowly manoeuvring target; one config (and T = 120) for two tests: one compile
SLOW = F.FilterConfig(accel_psd=0.05, lost_after=2.0)


def test_process_noise_is_the_continuous_white_noise_acceleration_matrix(x64):
    dt, q = 0.37, 2.5
    Q = np.asarray(F.white_noise_acceleration_q(dt, q))
    # Bar-Shalom et al. (6.2.2-12), per axis [[dt^3/3, dt^2/2], [dt^2/2, dt]] q, state [p, v]
    expected = np.zeros((6, 6))
    for i in range(3):
        expected[i, i] = q * dt ** 3 / 3
        expected[i, i + 3] = expected[i + 3, i] = q * dt ** 2 / 2
        expected[i + 3, i + 3] = q * dt
    np.testing.assert_allclose(Q, expected, rtol=1e-12)
    # and it is the integral of F(s) G q G^T F(s)^T over [0, dt] (G = [0, I]^T): trapezoid
    s = np.linspace(0.0, dt, 2001)
    G = np.vstack([np.zeros((3, 3)), np.eye(3)])
    vals = np.stack([np.asarray(F.transition(si)) @ G @ G.T @ np.asarray(F.transition(si)).T
                     for si in s[::100]])
    integral = q * simpson(vals, x=s[::100], axis=0)  # exact: the integrand is quadratic
    np.testing.assert_allclose(Q, integral, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(np.asarray(F.transition(dt))[:3, 3:], dt * np.eye(3))
    # per axis (a ground target's small vertical PSD): each axis its own block, no coupling
    q_axes = F.FilterConfig(accel_psd=q, vertical_accel_psd=0.1).axis_psd
    assert q_axes == (q, q, 0.1)
    Q3 = np.asarray(F.white_noise_acceleration_q(dt, np.asarray(q_axes)))
    scale = np.array([1.0, 1.0, 0.1 / q] * 2)
    np.testing.assert_allclose(Q3, expected * np.sqrt(np.outer(scale, scale)), rtol=1e-12)


def _simulate(rng, runs, n_frames, q, r_sigma, v_sigma):
    """``runs`` constant-velocity targets driven by the discrete CWNA noise (the filter's own
    model), measured with noise: truth (runs, T, 6), measurements (runs, T, 3)."""
    Fm = np.asarray(F.transition(DT), np.float64)
    L = np.linalg.cholesky(np.asarray(F.white_noise_acceleration_q(DT, q), np.float64))
    x = np.concatenate([np.broadcast_to([5.0, -3.0, 1.0], (runs, 3)),
                        v_sigma * rng.standard_normal((runs, 3))], axis=1)
    truth = [x]
    for _ in range(n_frames - 1):
        x = x @ Fm.T + rng.standard_normal((runs, 6)) @ L.T
        truth.append(x)
    truth = np.stack(truth, axis=1)
    return truth, truth[..., :3] + r_sigma * rng.standard_normal((runs, n_frames, 3))


def test_nees_is_consistent_over_monte_carlo_runs(x64):
    runs, n_frames, q, r_sigma = 200, 40, 0.5, 0.15
    config = F.FilterConfig(accel_psd=q, init_velocity_sigma=1.0)
    truth, z = _simulate(np.random.default_rng(0), runs, n_frames, q, r_sigma,
                         config.init_velocity_sigma)
    times = np.arange(n_frames) * DT
    R = np.broadcast_to(r_sigma ** 2 * np.eye(3), (runs, n_frames, 3, 3))
    valid = np.ones((runs, n_frames), bool)
    out = jax.vmap(functools.partial(run_filter, config=config), in_axes=(None, 0, 0, 0))(
        times, z, R, valid)
    err = truth - np.concatenate([np.asarray(out.position), np.asarray(out.velocity)], axis=-1)
    nees = np.einsum("rti,rtij,rtj->rt", err, np.linalg.inv(np.asarray(out.covariance)), err)
    mean_nees = nees.mean(axis=0)  # (n_frames,), runs * mean ~ chi-square(6 runs)
    lo, hi = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    inside = (mean_nees >= lo) & (mean_nees <= hi)
    assert inside.mean() >= 0.85, (lo, hi, mean_nees)
    assert abs(mean_nees.mean() - 6.0) < 0.3, mean_nees.mean()
    assert float(np.asarray(out.gated).mean()) < 0.01  # a consistent stream is rarely gated


def _static_stream(n_frames=120, sigma=0.05, seed=0):
    rng = np.random.default_rng(seed)
    truth = np.array([2.0, 1.0, 0.5])
    z = truth + sigma * rng.standard_normal((n_frames, 3))
    R = np.broadcast_to(sigma ** 2 * np.eye(3), (n_frames, 3, 3)).copy()
    return np.arange(n_frames) * DT, z, R, np.ones(n_frames, bool), truth


def test_gate_rejects_a_10_m_outlier():
    times, z, R, valid, truth = _static_stream()
    z[25] += np.array([10.0, 0.0, 0.0])
    out = run_filter(times, z, R, valid, SLOW)
    gated = np.asarray(out.gated)
    assert gated[25] and gated.sum() == 1
    status = np.asarray(out.status)
    assert status[25] == F.PREDICTING and status[26] == F.TRACKING
    assert np.linalg.norm(np.asarray(out.position[25]) - truth) < 0.1
    assert np.float32(F.FilterConfig().gate) == np.float32(chi2.ppf(0.997, 3))


def test_predicts_while_unseen_then_loses_and_reinitialises():
    n = 120
    times = np.arange(n) * DT
    velocity = np.array([1.0, -0.5, 0.0])
    truth = np.array([0.0, 0.0, 1.0]) + times[:, None] * velocity
    rng = np.random.default_rng(3)
    z = truth + 0.02 * rng.standard_normal((n, 3))
    R = np.broadcast_to(0.02 ** 2 * np.eye(3), (n, 3, 3)).copy()
    valid = np.ones(n, bool)
    valid[:5] = False  # not yet seen
    valid[40:50] = False  # unseen 1 s: prediction
    valid[70:100] = False  # unseen 3 s: lost after 2 s
    z[~valid] = np.nan  # what locate gives when it does not locate
    jump = np.array([20.0, 0.0, 0.0])
    z[100:] += jump  # reappears elsewhere: only a reset accepts it
    cfg = SLOW
    out = run_filter(times, z, R, valid, cfg)
    status, pos = np.asarray(out.status), np.asarray(out.position)

    assert np.all(status[:5] == F.UNSEEN) and np.all(np.isnan(pos[:5]))
    assert status[5] == F.TRACKING
    assert np.all(status[40:50] == F.PREDICTING)
    # constant-velocity prediction, inside its own 3-sigma ellipsoid
    err = pos[49] - truth[49]
    assert err @ np.linalg.solve(np.asarray(out.covariance[49, :3, :3]), err) < chi2.ppf(0.997, 3)
    assert np.linalg.norm(err) < 0.3
    # lost once more than lost_after has passed since the last measurement (frame 69)
    lost = np.flatnonzero(status == F.LOST)
    assert lost[0] == 69 + round(cfg.lost_after / DT) + 1 and lost[-1] == 99
    assert np.all(status[70:lost[0]] == F.PREDICTING)
    np.testing.assert_array_equal(pos[lost], np.broadcast_to(pos[lost[0] - 1], (lost.size, 3)))
    # re-initialised from the next measurement, ungated
    assert status[100] == F.TRACKING and not np.asarray(out.gated)[100]
    np.testing.assert_allclose(pos[100], z[100], atol=1e-5)
    assert np.linalg.norm(pos[-1] - (truth[-1] + jump)) < 0.1


def test_filter_is_one_compiled_scan():
    times, z, R, valid, _ = _static_stream(n_frames=10)
    jaxpr = jax.make_jaxpr(lambda *a: run_filter(*a, config=F.FilterConfig()))(
        times, z, R, valid)
    assert "scan" in str(jaxpr)
    with pytest.raises(ValueError):
        F.FilterConfig(gate_probability=1.0)


def test_a_run_of_gated_measurements_reinitialises_on_the_target():
    """A target that jumps 3 m and stays there (a turn the model did not follow, or a pose
    correction) is gated at first; after ``reinit_after_gated`` gated frames in a row the
    filter restarts on it, while a single 10 m outlier is still gated."""
    T = 40
    t = np.arange(T) * 0.05
    z = np.zeros((T, 3))
    z[20:] = [3.0, 0.0, 0.0]
    z[10] = [10.0, 0.0, 0.0]
    R = np.tile(0.01 * np.eye(3), (T, 1, 1))
    valid = np.ones(T, bool)
    out = run_filter(t, z, R, valid, F.FilterConfig(reinit_after_gated=5))
    gated = np.asarray(out.gated)
    assert gated[10] and np.asarray(out.status)[11] == F.TRACKING
    assert gated[20:24].all() and not gated[24:].any()
    assert np.linalg.norm(np.asarray(out.position)[24] - z[24]) < 0.2
    never = run_filter(t, z, R, valid, F.FilterConfig(reinit_after_gated=0))
    assert np.asarray(never.gated)[20:].all()


def test_prediction_coasts_then_holds():
    """Measurements of a target at 2 m/s stop at 1 s: the prediction moves on for
    ``coast_after`` seconds, then holds, while its covariance keeps growing."""
    t = np.arange(60) * 0.05
    z = np.stack([2.0 * t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    R = np.tile(0.001 * np.eye(3), (60, 1, 1))
    valid = t < 1.0
    out = run_filter(t, z, R, valid, F.FilterConfig(accel_psd=1.0, coast_after=0.5))
    x = np.asarray(out.position)[:, 0]
    last = np.flatnonzero(valid)[-1]
    assert x[last + 5] == pytest.approx(x[last] + 2.0 * 0.25, abs=0.05)  # still moving
    held = t > t[last] + 0.5 + 1e-9
    np.testing.assert_allclose(x[held], x[held][0], atol=1e-6)
    assert x[held][0] == pytest.approx(x[last] + 2.0 * 0.5, abs=0.1)
    var = np.asarray(out.covariance)[:, 0, 0]
    assert np.all(np.diff(var[last:]) > 0)


def test_a_ground_target_never_climbs_but_its_height_follows_the_measurements(x64):
    """``vertical_accel_psd = vertical_velocity_sigma = 0`` with a height random walk: the
    vertical velocity stays exactly zero, also while coasting unseen, and a step in the
    measured height (a view whose height error differs) is followed, not flown off with."""
    n = 60
    times = np.arange(n) * DT
    truth = np.stack([1.0 + 2.0 * times, -0.5 * times, np.zeros(n)], axis=1)  # on the floor
    z = truth + 0.05 * np.random.default_rng(3).standard_normal((n, 3))
    z[20:40, 2] += 0.4  # 20 frames whose height reads 0.4 m high
    valid = np.arange(n) < 50  # unseen for the last 10 frames
    R = np.broadcast_to(0.05 ** 2 * np.eye(3), (n, 3, 3))
    config = F.FilterConfig(accel_psd=1.0, vertical_accel_psd=0.0, vertical_velocity_sigma=0.0,
                            height_walk_psd=1.0, lost_after=5.0)
    out = run_filter(times, z, R, valid, config)
    vel, pos = np.asarray(out.velocity), np.asarray(out.position)
    np.testing.assert_array_equal(vel[:, 2], 0.0)
    assert abs(pos[39, 2] - 0.4) < 0.1  # followed the raised heights
    assert abs(pos[49, 2]) < 0.1  # and came back down with them
    np.testing.assert_allclose(pos[50:, 2], pos[49, 2])  # coasting keeps the height
    np.testing.assert_allclose(vel[49, :2], [2.0, -0.5], atol=0.3)  # horizontal untouched
    # no vertical acceleration: Q has nothing on the height or the vertical velocity
    Q = np.asarray(F.white_noise_acceleration_q(DT, np.asarray(config.axis_psd)))
    assert Q[2].tolist() == [0.0] * 6 and Q[:, 5].tolist() == [0.0] * 6
