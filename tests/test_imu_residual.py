"""predict() and the 15-dimensional IMU residual: consistency, whitening, statistics, and
GTSAM 4.3's ``CombinedImuFactor`` on real EuRoC V1_01 intervals."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from imu_synthetic import G, position, rotation, velocity, window
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.geometry import so3
from uavcal_jax.geometry.frames import GRAVITY, GRAVITY_W
from uavcal_jax.imu import (
    ImuBias,
    ImuNoise,
    NavState,
    imu_residual,
    imu_residual_whitened,
    interval_batch,
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
    np.testing.assert_allclose(GRAVITY_W, G)


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
    # differentiable in the states
    g = jax.grad(lambda p: jnp.sum(imu_residual_whitened(
        s_i, bi, NavState(s_j.rotation, p, s_j.velocity), bj, pim) ** 2))(s_j.position)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("bias_covariance", [False, True])
def test_whitened_residual_is_standard_normal(x64, bias_covariance):
    """Noisy IMU (white noise, and bias random walks) at the true states: the whitened
    residual has identity covariance, so the propagated and residual covariances -- with
    their cross terms and sign conventions -- are right."""
    dt, gyro, accel = window(0.0, 0.5, 100, rate=2.0)
    h = dt[0]
    noise = ImuNoise(gyro_noise_density=2e-3, accel_noise_density=2e-2,
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


def _gtsam_combined(gtsam, noise, bias_gyro, bias_accel, dt, gyro, accel):
    """GTSAM's combined preintegration of one interval (EuRoC's densities, no integration
    noise) and its ``CombinedImuFactor`` on keys 0..5 (pose_i, vel_i, pose_j, vel_j, bias_i,
    bias_j)."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY)
    params.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise_density**2)
    params.setAccelerometerCovariance(np.eye(3) * noise.accel_noise_density**2)
    params.setIntegrationCovariance(np.zeros((3, 3)))
    params.setBiasOmegaCovariance(np.eye(3) * noise.gyro_random_walk**2)
    params.setBiasAccCovariance(np.eye(3) * noise.accel_random_walk**2)
    pim = gtsam.PreintegratedCombinedMeasurements(
        params, gtsam.imuBias.ConstantBias(bias_accel, bias_gyro))
    for k in range(len(dt)):
        pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return gtsam.CombinedImuFactor(0, 1, 2, 3, 4, 5, pim)


def _unit_rotation(wxyz):
    """Rotation matrix of a ground-truth quaternion, normalised: EuRoC's are unit to ~1e-6 only,
    and ``gtsam.Rot3.Quaternion`` does not normalise (its matrix would be that far from a
    rotation, and ``R^T`` that far from ``R^-1``)."""
    return Rotation.from_quat(np.roll(wxyz, -1)).as_matrix()


def test_residual_and_whitening_match_gtsam_combined_factor(x64, euroc_micro):
    """Our residual, covariance and whitening against ``gtsam.CombinedImuFactor`` on one 50 ms
    and two 1 s intervals of the real V1_01 IMU, at perturbed states and biases.

    GTSAM's error is ``e = Log(X_j^-1 X_pred)`` on SE_2(3) (rows rotation, position,
    velocity), then ``b_i - b_j`` (accel, gyro); ours is state j against the prediction in the
    frame at i (rotation, velocity, position, then ``b_j - b_i`` gyro, accel; see
    ``imu/residual.py``). Exactly: ``r_R = -e_R``; with ``X_pred = X_j Exp(e)`` (the
    prediction GTSAM's error points to), ``r_v = R_i^T (v_j - v_pred)`` and
    ``r_p = R_i^T (p_j - p_pred)``; ``r_b = -e_b``. At zero error ``dr = A de`` with
    ``A = -diag(I, dR, dR, I, I)`` (reordered; ``dR = R_i^T R_j = delta_R``), so our covariance
    must be ``A Sigma A^T`` with ``Sigma`` the factor's noise model (GTSAM's
    ``residualCovariance``), and our whitened residuals must have the inner products of GTSAM's
    whitening of ``A^-1 r``. GTSAM's own factor cost differs from ours only at second order
    (its coordinates at ``X_j``, ours at the prediction).
    """
    gtsam = pytest.importorskip("gtsam")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the micro copy lists 4 cam1 frames it does not ship
        seq = read_euroc(euroc_micro)
    gt, noise = seq.ground_truth, seq.imu_calibration.noise
    first = np.array([30, 400, 1500])
    last = first + np.array([1, 20, 20])  # ground truth at 20 Hz: 50 ms, 1 s, 1 s
    batch = interval_batch(seq.imu, starts=gt.t_ns[first], ends=gt.t_ns[last])
    pims = preintegrate(batch.dt, batch.gyro, batch.accel, gt.bias_gyro[first],
                        gt.bias_accel[first], mask=batch.mask, noise=noise, bias_covariance=True)
    rng = np.random.default_rng(7)
    I3, Z3 = np.eye(3), np.zeros((3, 3))
    for n, (i, j) in enumerate(zip(first, last, strict=True)):
        m = int(batch.mask[n].sum())
        factor = _gtsam_combined(gtsam, noise, gt.bias_gyro[i], gt.bias_accel[i],
                                 batch.dt[n, :m], batch.gyro[n, :m], batch.accel[n, :m])
        model = factor.noiseModel()
        pim = jax.tree_util.tree_map(lambda x, n=n: x[n], pims)
        dR = np.asarray(pim.delta_R)
        # ours (rot, vel, pos, bg, ba) = A @ GTSAM's (rot, pos, vel, ba, bg), to first order
        A = -np.block([[I3, Z3, Z3, Z3, Z3], [Z3, Z3, dR, Z3, Z3], [Z3, dR, Z3, Z3, Z3],
                       [Z3, Z3, Z3, Z3, I3], [Z3, Z3, Z3, I3, Z3]])
        ref_cov = A @ model.covariance() @ A.T
        np.testing.assert_allclose(np.asarray(residual_covariance(pim)), ref_cov, rtol=1e-9,
                                   atol=1e-12 * np.abs(ref_cov).max())
        ours_w, gtsam_w = [], []
        for _ in range(4):
            d = rng.normal(size=(10, 3)) * np.array([1e-3] * 6 + [1e-4, 1e-3, 1e-4, 1e-3])[:, None]
            R_i = _unit_rotation(gt.quaternion[i]) @ Rotation.from_rotvec(d[0]).as_matrix()
            R_j = _unit_rotation(gt.quaternion[j]) @ Rotation.from_rotvec(d[1]).as_matrix()
            p_i, p_j = gt.position[i] + d[2], gt.position[j] + d[3]
            v_i, v_j = gt.velocity[i] + d[4], gt.velocity[j] + d[5]
            bg_i, ba_i = gt.bias_gyro[i] + d[6], gt.bias_accel[i] + d[7]
            bg_j, ba_j = bg_i + d[8], ba_i + d[9]
            variables = [gtsam.Pose3(gtsam.Rot3(R_i), p_i), v_i,
                         gtsam.Pose3(gtsam.Rot3(R_j), p_j), v_j,
                         gtsam.imuBias.ConstantBias(ba_i, bg_i),
                         gtsam.imuBias.ConstantBias(ba_j, bg_j)]
            e = factor.evaluateError(*variables)
            values = gtsam.Values()
            for key, value in enumerate(variables):
                values.insert(key, value)
            pred = gtsam.NavState(gtsam.Rot3(R_j), p_j, v_j).expmap(e[:9])
            r_ref = np.concatenate([
                gtsam.Rot3.Logmap(pred.attitude().between(gtsam.Rot3(R_j))),
                R_i.T @ (v_j - pred.velocity()), R_i.T @ (p_j - pred.position()),
                -e[12:15], -e[9:12]])
            args = (NavState(jnp.asarray(R_i), jnp.asarray(p_i), jnp.asarray(v_i)),
                    ImuBias(jnp.asarray(bg_i), jnp.asarray(ba_i)),
                    NavState(jnp.asarray(R_j), jnp.asarray(p_j), jnp.asarray(v_j)),
                    ImuBias(jnp.asarray(bg_j), jnp.asarray(ba_j)), pim)
            r = np.asarray(imu_residual(*args))
            np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-9)
            np.testing.assert_allclose(r[:3], -e[:3], rtol=0, atol=1e-12)
            w = np.asarray(imu_residual_whitened(*args))
            u = model.whiten(np.linalg.solve(A, r))
            cost = 0.5 * float(w @ w)
            assert cost == pytest.approx(0.5 * float(u @ u), rel=1e-9)
            assert cost == pytest.approx(factor.error(values), rel=1e-2)
            ours_w.append(w)
            gtsam_w.append(u)
        # whitenings may differ by a rotation (Cholesky factors of different orders): compare
        # every inner product
        W, U = np.array(ours_w), np.array(gtsam_w)
        np.testing.assert_allclose(W @ W.T, U @ U.T, rtol=1e-9, atol=1e-9 * np.abs(U @ U.T).max())
