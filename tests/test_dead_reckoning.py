"""IMU dead reckoning against the simulator's ground truth."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from uavcal_jax.geometry import so3
from uavcal_jax.imu.dead_reckoning import dead_reckon
from uavcal_jax.sim.flights import procedural_flight
from uavcal_jax.sim.imu_synth import ground_truth_from_trajectory, synthesize_imu

DURATION_S = 6.0


@pytest.fixture(scope="module")
def flight():
    """A noise-free 200 Hz IMU of a procedural flight (turns, climbs, legs) and its truth."""
    traj = procedural_flight(4, DURATION_S)  # legs, a climb and turns within 6 s
    synth = synthesize_imu(traj, rate_hz=200.0, noise=None)
    gt = ground_truth_from_trajectory(traj, synth.imu.t_ns)
    return synth.imu, gt


def _reckon(imu, gt, offset=None):
    with jax.enable_x64(True):
        R0 = so3.from_quaternion(gt.quaternion[0])
        R, v, p = dead_reckon(np.diff(imu.t_ns) * 1e-9, imu.gyro, imu.accel, R0,
                              gt.velocity[0], gt.position[0], offset)
        return np.asarray(R), np.asarray(v), np.asarray(p)


def test_tracks_truth_on_exact_imu(flight):
    imu, gt = flight
    assert np.ptp(gt.position, axis=0).max() > 1.0  # the flight moves
    R, v, p = _reckon(imu, gt)
    with jax.enable_x64(True):
        R_gt = np.asarray(so3.from_quaternion(gt.quaternion))
        angle = np.linalg.norm(np.asarray(so3.log(np.swapaxes(R_gt, -1, -2) @ R)), axis=-1)
    assert np.max(np.linalg.norm(p - gt.position, axis=1)) < 2e-3  # m over 6 s
    assert np.max(np.linalg.norm(v - gt.velocity, axis=1)) < 1e-3  # m/s
    assert np.max(angle) < 1e-5  # rad


def test_accel_offset_at_rest_drifts_as_half_b_t_squared():
    """A level IMU at rest with a constant accel error ``b``: ``p(t) - p0 = b t^2 / 2``."""
    n, b = 2001, np.array([0.1, -0.05, 0.08])
    with jax.enable_x64(True):
        _, v, p = dead_reckon(np.full(n - 1, 0.005), np.zeros((n, 3)),
                              np.tile([0.0, 0.0, 9.81], (n, 1)) + b, np.eye(3), np.zeros(3),
                              np.zeros(3))
    t = 0.005 * np.arange(n)
    np.testing.assert_allclose(np.asarray(p), 0.5 * t[:, None] ** 2 * b, atol=1e-9)
    np.testing.assert_allclose(np.asarray(v), t[:, None] * b, atol=1e-9)


def test_body_accel_offset_drift_on_a_flight(flight):
    """On the moving flight a body-fixed accel error ``b`` drifts by the double integral of
    ``R(t) b`` along the true attitude, and subtracting it as ``offset`` gives the exact run
    back."""
    imu, gt = flight
    b = np.array([0.0, 0.0, 0.0, 0.1, -0.05, 0.08])
    _, _, p_clean = _reckon(imu, gt)
    dt = np.diff(imu.t_ns) * 1e-9
    with jax.enable_x64(True):
        R_gt = np.asarray(so3.from_quaternion(gt.quaternion))
        args = (imu.gyro, imu.accel + b[3:], R_gt[0], gt.velocity[0], gt.position[0])
        p_biased = np.asarray(dead_reckon(dt, *args)[2])
        p_removed = np.asarray(dead_reckon(dt, *args, b)[2])
    np.testing.assert_allclose(p_removed, p_clean, atol=1e-9)
    a_err = R_gt @ b[3:]
    v_err = np.concatenate([np.zeros((1, 3)), np.cumsum(
        0.5 * dt[:, None] * (a_err[1:] + a_err[:-1]), axis=0)])
    p_err = np.concatenate([np.zeros((1, 3)), np.cumsum(
        0.5 * dt[:, None] * (v_err[1:] + v_err[:-1]), axis=0)])
    drift = p_biased - p_clean
    assert np.linalg.norm(drift[-1]) > 1.0  # metres: ~b t^2 / 2 over 6 s
    np.testing.assert_allclose(drift, p_err, atol=2e-3 * np.linalg.norm(drift[-1]))
