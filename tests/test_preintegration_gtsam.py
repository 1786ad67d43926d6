"""Preintegration of the real EuRoC V1_01 IMU against GTSAM 4.3 and against ground truth.

Intervals: every pair of consecutive 20 Hz ground-truth states over the first 20 s (which
contains the 4.7 s covered by the micro sequence's frames), and back-to-back 1 s intervals
over the whole 145 s recording; always with the ground-truth biases at the interval start.
"""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.geometry import so3
from uavcal_jax.geometry.frames import GRAVITY
from uavcal_jax.imu import (
    NavState,
    interval_batch,
    interval_samples,
    predict,
    preintegrate,
)

gtsam = pytest.importorskip("gtsam")

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def v101():
    from conftest import shared_path

    root = shared_path("euroc_v101_micro")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the micro copy lists 4 cam1 frames it does not ship
        seq = read_euroc(root)
    return seq


def _intervals(seq, kind):
    gt = seq.ground_truth
    if kind == "pairs":  # consecutive 20 Hz states over the first 20 s
        i = np.arange(0, 400)
        j = i + 1
    else:  # back-to-back 1 s intervals over the whole sequence
        i = np.arange(0, len(gt) - 20, 20)
        j = i + 20
    return i, j


def _gtsam_params(noise, combined=False):
    cls = gtsam.PreintegrationCombinedParams if combined else gtsam.PreintegrationParams
    p = cls.MakeSharedU(GRAVITY)
    p.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * noise.accel_noise_density**2)
    p.setIntegrationCovariance(np.zeros((3, 3)))
    if combined:
        p.setBiasOmegaCovariance(np.eye(3) * noise.gyro_random_walk**2)
        p.setBiasAccCovariance(np.eye(3) * noise.accel_random_walk**2)
    return p


def _gtsam_pims(seq, i, j, noise, combined=False):
    gt, imu = seq.ground_truth, seq.imu
    params = _gtsam_params(noise, combined)
    cls = (gtsam.PreintegratedCombinedMeasurements if combined
           else gtsam.PreintegratedImuMeasurements)
    out = []
    for a, b in zip(i, j, strict=True):
        iv = interval_samples(imu, t_start=gt.t_ns[a], t_end=gt.t_ns[b])
        pim = cls(params, gtsam.imuBias.ConstantBias(gt.bias_accel[a], gt.bias_gyro[a]))
        for k in range(len(iv.dt)):
            pim.integrateMeasurement(iv.accel[k], iv.gyro[k], iv.dt[k])
        out.append(pim)
    return out


def _ours(seq, i, j, noise, **kw):
    gt = seq.ground_truth
    batch = interval_batch(seq.imu, starts=gt.t_ns[i], ends=gt.t_ns[j])
    with jax.enable_x64(True):
        run = jax.jit(lambda d, g, a, bg, ba, m: preintegrate(d, g, a, bg, ba, mask=m,
                                                              noise=noise, **kw))
        r = run(batch.dt, batch.gyro, batch.accel, gt.bias_gyro[i], gt.bias_accel[i], batch.mask)
        return jax.tree_util.tree_map(np.asarray, r)


@pytest.fixture(scope="module")
def cases(v101):
    noise = v101.imu_calibration.noise
    out = {}
    for kind in ("pairs", "1s"):
        i, j = _intervals(v101, kind)
        out[kind] = (i, j, _gtsam_pims(v101, i, j, noise))
    return noise, out


def _max_diffs(ours, pims):
    dR = max(float(np.abs(gtsam.Rot3.Logmap(gtsam.Rot3(p.deltaRij().matrix().T @ ours.delta_R[n])))
                   .max()) for n, p in enumerate(pims))
    dv = max(float(np.abs(ours.delta_v[n] - p.deltaVij()).max()) for n, p in enumerate(pims))
    dp = max(float(np.abs(ours.delta_p[n] - p.deltaPij()).max()) for n, p in enumerate(pims))
    dt = max(abs(float(ours.delta_t[n]) - p.deltaTij()) for n, p in enumerate(pims))
    return dR, dv, dp, dt


@pytest.mark.parametrize("kind", ["pairs", "1s"])
@pytest.mark.parametrize("scheme, tol", [("tangent", 1e-10), ("manifold", 1e-4)])
def test_deltas_match_gtsam(v101, cases, kind, scheme, tol):
    noise, data = cases
    i, j, pims = data[kind]
    ours = _ours(v101, i, j, noise, scheme=scheme)
    assert ours.valid.all()
    dR, dv, dp, dt = _max_diffs(ours, pims)
    assert dt < 1e-12
    assert max(dR, dv, dp) < tol, f"{scheme}/{kind}: rot {dR:.2e} rad, v {dv:.2e}, p {dp:.2e}"


@pytest.mark.parametrize("scheme, rtol", [("tangent", 1e-3), ("manifold", 0.05)])
def test_covariance_matches_gtsam(v101, cases, scheme, rtol):
    noise, data = cases
    for kind in ("pairs", "1s"):
        i, j, pims = data[kind]
        ours = _ours(v101, i, j, noise, scheme=scheme)
        worst = 0.0
        for n, p in enumerate(pims):
            ref = np.diag(p.preintMeasCov())
            worst = max(worst, float(np.max(np.abs(np.diag(ours.gtsam_cov[n]) / ref - 1))))
        assert worst < rtol, f"{scheme}/{kind}: largest relative diagonal difference {worst:.2e}"


def test_recursive_covariance_is_gtsams(v101, cases):
    noise, data = cases
    i, j, pims = data["1s"]
    ours = _ours(v101, i, j, noise, covariance="recursive")
    for n, p in enumerate(pims):
        ref = p.preintMeasCov()
        np.testing.assert_allclose(ours.gtsam_cov[n], ref, rtol=1e-9,
                                   atol=1e-12 * np.abs(ref).max())


def test_combined_covariance_is_gtsams(v101):
    noise = v101.imu_calibration.noise
    i = np.arange(0, 2000, 100)
    j = i + 20
    pims = _gtsam_pims(v101, i, j, noise, combined=True)
    ours = _ours(v101, i, j, noise, bias_covariance=True)
    for n, p in enumerate(pims):
        ref = p.preintMeasCov()
        np.testing.assert_allclose(ours.gtsam_cov[n], ref, rtol=1e-9,
                                   atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("scheme", ["tangent", "manifold"])
def test_bias_jacobians_match_gtsam_central_differences(v101, cases, scheme):
    """GTSAM's predict from the identity state with biases perturbed by +-eps, differenced."""
    noise, data = cases
    i, j, pims = data["1s"]
    sel = np.arange(0, len(i), 7)  # 21 intervals spread over the sequence
    ours = _ours(v101, i[sel], j[sel], noise, scheme=scheme)
    gt = v101.ground_truth
    eps = 1e-5
    state0 = gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3))
    worst = 0.0
    for n, s in enumerate(sel):
        pim = pims[s]
        b0 = np.concatenate([gt.bias_gyro[i[s]], gt.bias_accel[i[s]]])
        R0 = pim.predict(state0, gtsam.imuBias.ConstantBias(b0[3:], b0[:3])).attitude().matrix()
        J = np.zeros((9, 6))
        for k in range(6):
            outs = []
            for sign in (1, -1):
                b = b0.copy()
                b[k] += sign * eps
                st = pim.predict(state0, gtsam.imuBias.ConstantBias(b[3:], b[:3]))
                rot = gtsam.Rot3.Logmap(gtsam.Rot3(R0.T @ st.attitude().matrix()))
                outs.append(np.concatenate([rot, st.velocity(), st.position()]))
            J[:, k] = (outs[0] - outs[1]) / (2 * eps)
        mine = ours.bias_jacobian[n]
        worst = max(worst, float(np.abs(mine - J).max()))
    tol = 1e-6 if scheme == "tangent" else 2e-4
    assert worst < tol, f"{scheme}: largest bias-Jacobian difference {worst:.2e}"


def _prediction_errors(seq, i, j, rotations, velocities, positions):
    gt = seq.ground_truth
    Rj = np.asarray(so3.from_quaternion(gt.quaternion[j]))
    e_rot = np.linalg.norm(np.asarray(so3.log(np.swapaxes(Rj, 1, 2) @ rotations)), axis=1)
    e_vel = np.linalg.norm(velocities - gt.velocity[j], axis=1)
    e_pos = np.linalg.norm(positions - gt.position[j], axis=1)
    return (np.degrees(np.sqrt(np.mean(e_rot**2))), np.sqrt(np.mean(e_vel**2)),
            np.sqrt(np.mean(e_pos**2)))


@pytest.mark.parametrize("scheme", ["tangent", "manifold"])
def test_prediction_vs_ground_truth_no_worse_than_gtsam(v101, cases, scheme):
    noise, data = cases
    i, j, pims = data["1s"]
    gt = v101.ground_truth
    with jax.enable_x64(True):
        ours = _ours(v101, i, j, noise, scheme=scheme)
        state_i = NavState.from_quaternion(gt.quaternion[i], gt.position[i], gt.velocity[i])
        pred = jax.tree_util.tree_map(np.asarray, predict(state_i, ours))
    mine = _prediction_errors(v101, i, j, pred.rotation, pred.velocity, pred.position)
    g_rot, g_vel, g_pos = [], [], []
    for n, p in enumerate(pims):
        s = gtsam.NavState(gtsam.Rot3.Quaternion(*gt.quaternion[i[n]]), gt.position[i[n]],
                           gt.velocity[i[n]])
        pj = p.predict(s, gtsam.imuBias.ConstantBias(gt.bias_accel[i[n]], gt.bias_gyro[i[n]]))
        g_rot.append(pj.attitude().matrix())
        g_vel.append(pj.velocity())
        g_pos.append(pj.position())
    theirs = _prediction_errors(v101, i, j, np.array(g_rot), np.array(g_vel), np.array(g_pos))
    # GTSAM's own: rotation RMS 0.116 deg, velocity 0.046 m/s, position 2.4 cm
    assert theirs[0] == pytest.approx(0.116, abs=0.002)
    assert theirs[1] == pytest.approx(0.046, abs=0.002)
    assert theirs[2] == pytest.approx(0.024, abs=0.001)
    slack = 1e-9 if scheme == "tangent" else 0.01  # the Euler scheme: within 1 % of GTSAM's
    for m, t in zip(mine, theirs, strict=True):
        assert m <= t * (1 + slack), (scheme, mine, theirs)
