"""Calibrator baselines: the mean offset, and the least-squares offset against ground truth on
exact and noisy simulated IMUs, against scipy's nonlinear least squares, per window, and on
the real EuRoC V1_01 IMU against its ground-truth gyro bias.

Every least-squares call here is a 10 s span of a 200 Hz IMU at 0.25 s keyframes (40 pairs,
padded to one shape), so the whole file compiles the preintegration once.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from calib_ls_reference import least_squares_offset, sequence_offset
from scipy.optimize import least_squares

from uavcal_jax.calib import baselines as bl
from uavcal_jax.data import read_euroc
from uavcal_jax.data.sequence import FrameStream, GroundTruth, ImuData, Sequence
from uavcal_jax.data.windows import WindowConfig, make_windows
from uavcal_jax.errors import DataError, DataRepairWarning
from uavcal_jax.imu import imu_residual, preintegrate, residual_covariance
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.imu.offset import add_offset
from uavcal_jax.sim.config import SimConfig, camera_calibrations
from uavcal_jax.sim.flights import procedural_flight
from uavcal_jax.sim.imu_synth import ground_truth_from_trajectory, synthesize_imu

#: gyro rad/s then accel m/s^2, the size of real IMU biases (EuRoC's: ~0.08, ~0.16 in norm)
OFFSET = np.array([0.02, -0.03, 0.05, 0.1, -0.15, 0.08])
RATE = 200.0
SPAN = (500_000_000, 10_500_000_000)  # 10 s of the 11 s flight, ns
CONFIG = bl.LeastSquaresConfig()  # 0.25 s keyframes, 3 Gauss-Newton iterations


@pytest.fixture(scope="module")
def flight():
    return procedural_flight(3, 11.0)


def _stream(traj, kind: str):
    """``(t_ns, gyro, accel, ground truth)`` of the flight with ``OFFSET`` injected.

    ``"noisy"``: the simulator's EuRoC noise with its default turn-on biases (kept: the ground
    truth carries the simulator's true biases, and the target is ``OFFSET`` plus their mean).
    ``"exact"``: noise-free, each sample the one that makes the preintegration's zero-order
    hold second-order accurate (the rates at mid-step, the specific force at mid-step plus
    ``dt/2 omega x a``, the rotation over the first half-step), so what is left is
    integration error, O(dt^2). ``"endpoint"``: noise-free as the simulator samples it
    (values at the hold's start, first-order): its error is the discretisation part.
    """
    syn = synthesize_imu(traj, RATE, EUROC_ADIS16448 if kind == "noisy" else None, seed=1)
    t_ns, gyro, accel = syn.imu.t_ns, syn.imu.gyro, syn.imu.accel
    gt = ground_truth_from_trajectory(traj, t_ns, syn.bias_gyro, syn.bias_accel)
    if kind == "exact":
        half = (t_ns[1] - t_ns[0]) // 2
        mid = synthesize_imu(traj, t_ns=np.minimum(t_ns + half, int(traj.t_end * 1e9)))
        gyro = mid.imu.gyro
        accel = mid.imu.accel + 0.5 / RATE * np.cross(mid.imu.gyro, mid.imu.accel)
    gyro, accel = (np.asarray(x) for x in add_offset(gyro, accel, OFFSET))
    return t_ns, gyro, accel, gt


def _estimate(t_ns, gyro, accel, gt: GroundTruth, config=CONFIG, span=SPAN):
    R = np.asarray(bl.ground_truth_rotations(gt))
    return least_squares_offset(t_ns, gyro, accel, gt.t_ns, R, gt.position, gt.velocity,
                                   config, span=span, return_std=True)


def test_mean_offset_baseline(x64):
    rng = np.random.default_rng(0)
    train = rng.normal(size=(5, 4, 6))
    mask = rng.random((5, 4)) > 0.3
    np.testing.assert_allclose(bl.mean_offset(train), train.reshape(-1, 6).mean(0), atol=1e-15)
    np.testing.assert_allclose(bl.mean_offset(train, mask), train[mask].mean(0), atol=1e-15)


def test_exact_imu_recovers_offset(x64, flight):
    t_ns, gyro, accel, gt = _stream(flight, "exact")
    est, _ = _estimate(t_ns, gyro, accel, gt)
    err = np.abs(np.asarray(est) - OFFSET)
    # measured: gyro 9e-8 rad/s, accel 6e-7 m/s^2 (the integration error of a 200 Hz hold)
    assert err[:3].max() < 2e-7, err
    assert err[3:].max() < 2e-6, err


def test_noisy_imu_recovers_offset(x64, flight):
    """Noise, bias random walk and turn-on biases on: the estimate is the injected offset plus
    the simulator's true mean bias over the span, to within 5 predicted standard deviations
    of the white noise plus the sampling's discretisation error (the endpoint stream's)."""
    t_ns, gyro, accel, gt = _stream(flight, "noisy")
    est, std = _estimate(t_ns, gyro, accel, gt)
    truth = OFFSET + bl.ground_truth_bias(gt, SPAN)
    t_e, g_e, a_e, gt_e = _stream(flight, "endpoint")
    discretisation = np.abs(np.asarray(_estimate(t_e, g_e, a_e, gt_e)[0]) - OFFSET)
    err = np.abs(np.asarray(est) - truth)
    # predicted std: gyro 5.4e-5 rad/s (= 1.7e-4 / sqrt(10 s)), accel 6.4e-4 m/s^2;
    # discretisation: gyro <= 7.2e-5, accel <= 7.5e-5; measured err: gyro <= 4.4e-5 rad/s,
    # accel <= 8.5e-4 m/s^2
    np.testing.assert_allclose(std[:3], 1.6968e-4 / np.sqrt(10.0), rtol=0.05)
    assert np.all(err < 5 * np.asarray(std) + discretisation), (err, std, discretisation)
    assert err[:3].max() < 2e-3 and err[3:].max() < 2e-2
    # without accounting for the turn-on biases the estimate is off by them
    assert np.abs(np.asarray(est) - OFFSET).max() > 10 * err.max()


def _reference_solution(pairs: bl.KeyframePairs, whiten: bool) -> np.ndarray:
    """scipy's trust-region least squares over the nonlinear residuals of
    :func:`uavcal_jax.imu.imu_residual`, re-preintegrating at every bias it tries."""
    p = jax.tree_util.tree_map(lambda x: jnp.asarray(x[None]), pairs)
    keep = np.asarray(pairs.pair_mask)
    s_i, s_j = p.state_i, p.state_j

    residual_fn = jax.jit(imu_residual)

    def residual(bg, ba):
        pim = preintegrate(p.dt, p.gyro, p.accel, jnp.asarray(bg), jnp.asarray(ba), mask=p.mask)
        return pim, np.asarray(residual_fn(s_i, None, s_j, None, pim))[0][keep]

    tight = dict(method="trf", jac="2-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    bg = least_squares(lambda x: residual(x, np.zeros(3))[1][:, :3].ravel(), np.zeros(3),
                       **tight).x
    pim, _ = residual(bg, np.zeros(3))
    S = np.asarray(residual_covariance(pim))[0][keep][:, 3:9, 3:9]
    L = np.linalg.cholesky(S) if whiten else np.broadcast_to(np.eye(6), S.shape)
    ba = least_squares(lambda x: np.linalg.solve(L, residual(bg, x)[1][:, 3:9, None]).ravel(),
                       np.zeros(3), **tight).x
    return np.concatenate([bg, ba])


@pytest.mark.parametrize("whiten", [True, False])
def test_matches_scipy_nonlinear_least_squares(x64, flight, whiten):
    t_ns, gyro, accel, gt = _stream(flight, "noisy")
    config = dataclasses.replace(CONFIG, whiten=whiten)
    est, _ = _estimate(t_ns, gyro, accel, gt, config)
    pairs = bl.keyframe_pairs(t_ns, gyro, accel, gt.t_ns, np.asarray(bl.ground_truth_rotations(gt)),
                              gt.position, gt.velocity, config, span=SPAN)
    ref = _reference_solution(pairs, whiten)
    # measured: <= 3e-10 (gyro 2e-12), limited by the forward differences of the reference
    np.testing.assert_allclose(np.asarray(est), ref, rtol=0, atol=1e-6)


def _sequence(traj, t_ns, gyro, accel, gt) -> Sequence:
    calib = camera_calibrations(SimConfig())["cam0"]
    t_cam = np.arange(int(traj.t_start * 1e9), int(traj.t_end * 1e9) + 1, 50_000_000)
    cam = FrameStream("cam0", t_cam.astype(np.int64), (), calib,
                      lambda i, c: np.zeros((8, 8), np.uint8))
    return Sequence("sim", None, {"cam0": cam}, ImuData(t_ns, gyro, accel), None, gt)


def test_windows_match_per_span_solves(x64, flight):
    """Each window's estimate is the single-span solve of its own stream with its injected
    offset (to rounding), and recovers that offset plus the true bias."""
    t_ns, gyro, accel, gt = _stream(flight, "noisy")
    gyro, accel = (np.asarray(x) for x in add_offset(gyro, accel, -OFFSET))  # clean stream
    seq = _sequence(flight, t_ns, gyro, accel, gt)
    ws = make_windows(seq, WindowConfig(duration=10.0, stride=0.5, size=(8, 8)),
                      frames=np.zeros((len(seq.camera()), 8, 8), np.uint8))
    assert len(ws) == 3
    offsets = OFFSET * np.array([[1.0], [-0.5], [2.0]])
    config = dataclasses.replace(CONFIG, chunk=1)
    est = np.asarray(bl.least_squares_windows(ws, gt, offsets, config))
    assert est.shape == (3, 6)
    bias = bl.ground_truth_bias_windows(ws, gt)
    for k in range(3):
        span = (ws.start_ns[k], ws.start_ns[k] + 10_000_000_000)
        g, a = (np.asarray(x) for x in add_offset(gyro, accel, offsets[k]))
        single, std = _estimate(t_ns, g, a, gt, config, span=span)
        np.testing.assert_allclose(est[k], np.asarray(single), rtol=0, atol=1e-12)
        assert np.all(np.abs(est[k] - offsets[k] - bias[k]) < 5 * np.asarray(std) + 2e-4)


def test_bad_input(x64, flight):
    t_ns, gyro, accel, gt = _stream(flight, "noisy")
    with pytest.raises(DataError, match="keyframe pairs"):
        _estimate(t_ns, gyro, accel, gt, span=(SPAN[0], SPAN[0] + 600_000_000))
    seq = _sequence(flight, t_ns, gyro, accel, dataclasses.replace(gt, velocity=None))
    with pytest.raises(DataError, match="velocities"):
        sequence_offset(seq, CONFIG, span=SPAN)
    with pytest.raises(ValueError):
        bl.LeastSquaresConfig(interval=0.0)


def test_euroc_gyro_offset_against_ground_truth_bias(x64, euroc_micro):
    """The real V1_01 IMU (145 s, the micro folder keeps all of it) against its ground
    truth, in 10 s spans: the gyro estimate agrees with the ground truth's own mean b_w
    (itself an estimate) to about 1e-3 rad/s per span (measured worst axis 1.1e-3, RMS
    4.1e-4; about 1.4 % of the 0.08 rad/s bias) and to 2e-4 averaged over the spans
    (measured 3.4e-5; the whole sequence in one solve: 1.5e-5)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataRepairWarning)  # cam1 lists 4 missing images
        seq = read_euroc(euroc_micro)
    gt = seq.ground_truth
    t0 = int(max(gt.t_ns[0], seq.imu.t_ns[0]))
    errors = []
    for k in range(14):
        span = (t0 + k * 10_000_000_000, t0 + (k + 1) * 10_000_000_000)
        est = np.asarray(sequence_offset(seq, CONFIG, span=span))
        errors.append(est[:3] - bl.ground_truth_bias(gt, span)[:3])
    errors = np.asarray(errors)
    assert np.abs(errors).max() < 2e-3, errors
    assert np.sqrt(np.mean(errors**2)) < 6e-4, errors
    assert np.abs(errors.mean(axis=0)).max() < 2e-4, errors


def test_least_squares_trial_oracle_recovers_each_injected_offset(x64, flight):
    """The experiments' least-squares trial (:func:`uavcal_jax.calib.trials.least_squares_trial`)
    injects each offset into every validation window: minus the ground-truth bias (the oracle)
    its estimates are the offsets, within the fit's noise; raw, they also carry the turn-on
    bias, so their RMSE is larger."""
    from uavcal_jax.calib.data import Windows
    from uavcal_jax.calib.trials import least_squares_trial

    t_ns, gyro, accel, gt = _stream(flight, "noisy")
    gyro, accel = (np.asarray(x) for x in add_offset(gyro, accel, -OFFSET))  # clean stream
    seq = _sequence(flight, t_ns, gyro, accel, gt)
    ws = make_windows(seq, WindowConfig(duration=10.0, stride=0.5, size=(8, 8)),
                      frames=np.zeros((len(seq.camera()), 8, 8), np.uint8))
    offsets = OFFSET * np.array([[1.0], [-0.5]])
    out = least_squares_trial([Windows(ws, np.arange(len(ws)), "sim")], offsets, "gyro",
                              lambda source: gt)
    assert out["oracle_per_window"].shape == (len(ws), 6)
    np.testing.assert_allclose(out["oracle_per_window"], np.broadcast_to(offsets[0], (3, 6)),
                               atol=0.02)
    assert out["oracle_metrics"]["offset_rmse"] < 0.01
    assert out["metrics"]["offset_rmse"] > out["oracle_metrics"]["offset_rmse"]
