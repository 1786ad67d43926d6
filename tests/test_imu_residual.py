"""predict() and the 15-dimensional IMU residual: consistency, whitening and statistics."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from imu_synthetic import G, position, rotation, velocity, window

from uavcal_jax.geometry import so3
from uavcal_jax.imu import (
    GRAVITY,
    ImuBias,
    NavState,
    PreintegrationNoise,
    imu_cost,
    imu_residual,
    imu_residual_whitened,
    predict,
    preintegrate,
    residual_covariance,
)


def _true_state(t):
    return NavState(jnp.asarray(rotation(t)[0]), jnp.asarray(position(np.array([t]))[0]),
                    jnp.asarray(velocity(np.array([t]))[0]))


@pytest.mark.parametrize("scheme", ["tangent", "manifold"])
def test_predict_matches_true_motion(x64, scheme):
    dt, gyro, accel = window(0.5, 1.0, 2000)
    pim = preintegrate(dt, gyro, accel, scheme=scheme)
    s_i, s_j = _true_state(0.5), _true_state(1.5)
    pred = predict(s_i, pim)
    assert float(jnp.linalg.norm(so3.log(s_j.rotation.T @ pred.rotation))) < 2e-5
    np.testing.assert_allclose(np.asarray(pred.velocity), np.asarray(s_j.velocity), atol=2e-3)
    np.testing.assert_allclose(np.asarray(pred.position), np.asarray(s_j.position), atol=2e-3)
    np.testing.assert_allclose(GRAVITY, G)


def test_residual_zero_at_prediction_and_bias_rows(x64):
    dt, gyro, accel = window(0.0, 1.0, 200)
    bi = ImuBias(jnp.array([0.01, 0.0, -0.01]), jnp.array([0.02, -0.03, 0.01]))
    pim = preintegrate(dt, gyro, accel, bi.gyro, bi.accel)
    s_i = _true_state(0.0)
    # another bias: prediction with first-order correction, residual still zero
    b_new = ImuBias(bi.gyro + 1e-3, bi.accel - 2e-3)
    s_j = predict(s_i, pim, b_new)
    bj = ImuBias(b_new.gyro + 0.001, b_new.accel + 0.002)
    r = imu_residual(s_i, b_new, s_j, bj, pim)
    assert r.shape == (15,)
    np.testing.assert_allclose(np.asarray(r[:9]), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(r[9:]), [0.001] * 3 + [0.002] * 3, atol=1e-15)
    # the other bias forms
    np.testing.assert_allclose(np.asarray(imu_residual(s_i, b_new.vector, s_j, bj.vector, pim)),
                               np.asarray(r), atol=0)
    np.testing.assert_allclose(
        np.asarray(imu_residual(s_i, (b_new.gyro, b_new.accel), s_j, (bj.gyro, bj.accel), pim)),
        np.asarray(r), atol=0)


def test_residual_signs_and_frames(x64):
    dt, gyro, accel = window(0.0, 0.5, 200)
    pim = preintegrate(dt, gyro, accel)
    s_i = _true_state(0.0)
    s_j = predict(s_i, pim)
    b = jnp.zeros(6)
    dv = jnp.array([0.1, -0.2, 0.3])
    moved = NavState(s_j.rotation, s_j.position, s_j.velocity + s_i.rotation @ dv)
    r = imu_residual(s_i, b, moved, b, pim)
    np.testing.assert_allclose(np.asarray(r[3:6]), np.asarray(dv), atol=1e-12)
    dphi = jnp.array([1e-3, -2e-3, 5e-4])
    turned = NavState(s_j.rotation @ so3.exp(dphi), s_j.position, s_j.velocity)
    r = imu_residual(s_i, b, turned, b, pim)
    np.testing.assert_allclose(np.asarray(r[:3]), np.asarray(dphi), atol=1e-12)


def test_whitening_is_mahalanobis(x64):
    dt, gyro, accel = window(0.0, 1.0, 200)
    pim = preintegrate(dt, gyro, accel)
    s_i = _true_state(0.0)
    s_j = NavState(s_i.rotation @ so3.exp(jnp.array([0.01, 0.02, -0.01])), s_i.position + 0.3,
                   s_i.velocity - 0.1)
    bi, bj = jnp.zeros(6), jnp.full(6, 1e-4)
    r = imu_residual(s_i, bi, s_j, bj, pim)
    e = imu_residual_whitened(s_i, bi, s_j, bj, pim)
    C = residual_covariance(pim)
    np.testing.assert_allclose(float(e @ e), float(r @ jnp.linalg.solve(C, r)), rtol=1e-9)
    np.testing.assert_allclose(float(imu_cost(s_i, bi, s_j, bj, pim)), 0.5 * float(e @ e),
                               rtol=1e-12)
    # differentiable in the states, batched under vmap
    g = jax.grad(lambda p: imu_cost(s_i, bi, NavState(s_j.rotation, p, s_j.velocity), bj, pim))(
        s_j.position)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("bias_covariance", [False, True])
def test_whitened_residual_is_standard_normal(x64, bias_covariance):
    """Noisy IMU (white noise, and bias random walks) at the true states: the whitened
    residual has identity covariance, so the propagated and residual covariances -- with
    their cross terms and sign conventions -- are right."""
    dt, gyro, accel = window(0.0, 0.5, 100, rate=2.0)
    h = dt[0]
    noise = PreintegrationNoise(gyro_noise_density=2e-3, accel_noise_density=2e-2,
                                gyro_random_walk=2e-2, accel_random_walk=2e-1)
    s_i = _true_state(0.0)
    exact = preintegrate(dt, gyro, accel)
    s_j = predict(s_i, exact)  # the noise-free preintegration defines the true state j
    n_mc, n = 3000, len(dt)
    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    white_g = jax.random.normal(keys[0], (n_mc, n, 3)) * noise.gyro_noise_density / np.sqrt(h)
    white_a = jax.random.normal(keys[1], (n_mc, n, 3)) * noise.accel_noise_density / np.sqrt(h)
    if bias_covariance:
        # bias during sample k = sum of the increments before it; b_j after the last one
        inc_g = jax.random.normal(keys[2], (n_mc, n, 3)) * noise.gyro_random_walk * np.sqrt(h)
        inc_a = jax.random.normal(keys[3], (n_mc, n, 3)) * noise.accel_random_walk * np.sqrt(h)
        walk_g = jnp.cumsum(inc_g, 1) - inc_g
        walk_a = jnp.cumsum(inc_a, 1) - inc_a
        bj = jnp.concatenate([walk_g[:, -1] + inc_g[:, -1], walk_a[:, -1] + inc_a[:, -1]], -1)
    else:
        walk_g = walk_a = 0.0
        bj = jnp.zeros((n_mc, 6))

    def one(ng, na, b_j):
        pim = preintegrate(dt, gyro + ng, accel + na, noise=noise, bias_covariance=bias_covariance)
        return imu_residual_whitened(s_i, jnp.zeros(6), s_j, b_j, pim)

    e = np.asarray(jax.jit(jax.vmap(one))(white_g + walk_g, white_a + walk_a, bj))
    k = 15 if bias_covariance else 9
    cov = np.cov(e[:, :k].T)
    np.testing.assert_allclose(np.diag(cov), 1.0, atol=0.1)
    assert np.max(np.abs(cov - np.eye(k))) < 0.1
    assert abs(np.mean(np.sum(e[:, :k] ** 2, 1)) - k) < 0.05 * k
