"""The kinematic drone (uavcal_jax.sim.drone_model): limits, convergence, IMU consistency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.sim.drone_model import (
    DroneConfig,
    attitude,
    fly,
    hover_state,
    imu_samples,
    wrap,
)

CFG = DroneConfig(max_speed=2.0, max_accel=2.5, max_yaw_rate=0.8)


def _far_flight(steps=1600):
    return fly(hover_state([0.0, 0.0, 2.0], 0.0), [30.0, -20.0, 6.0], 3.0, steps, CFG)


def test_limits_respected_on_a_far_setpoint():
    f = _far_flight()
    speed = np.linalg.norm(f.v, axis=1)
    accel = np.linalg.norm(f.a, axis=1)
    yaw_rate = np.abs(np.diff(f.yaw)) * CFG.rate_hz
    assert accel.max() <= CFG.max_accel + 1e-9
    assert yaw_rate.max() <= CFG.max_yaw_rate + 1e-9
    # the attitude lag lets the speed overshoot its limit by a few per cent at most
    assert speed.max() <= 1.03 * CFG.max_speed
    assert speed.max() > 0.95 * CFG.max_speed  # and it does fly at the limit
    assert yaw_rate.max() > 0.95 * CFG.max_yaw_rate


def test_converges_to_a_static_setpoint():
    sp = np.array([3.0, -2.0, 3.5])
    f = fly(hover_state([0.0, 0.0, 2.0], 0.5), sp, -2.5, 12 * 200, CFG)
    end = f.state()
    assert np.linalg.norm(end.p - sp) < 1e-3
    assert np.linalg.norm(end.v) < 1e-3
    assert abs(wrap(end.yaw - (-2.5))) < 1e-3
    # at rest the thrust axis is vertical
    np.testing.assert_allclose(f.R_WQ[-1][:, 2], [0, 0, 1], atol=1e-4)


def test_attitude_tilts_along_the_acceleration():
    R = attitude(np.array([2.0, 0.0, 0.0]), 0.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # accelerating forward pitches the nose down: thrust axis leans forward
    assert R[0, 2] > 0 and R[2, 0] < 0
    np.testing.assert_allclose(np.degrees(np.arctan2(R[0, 2], R[2, 2])),
                               np.degrees(np.arctan2(2.0, 9.81)), atol=1e-9)


def test_hover_imu_reads_gravity():
    f = fly(hover_state([1.0, 2.0, 3.0], 1.0), [1.0, 2.0, 3.0], 1.0, 20, CFG)
    gyro, accel = imu_samples(f, CFG.dt)
    np.testing.assert_allclose(gyro, 0.0, atol=1e-12)
    np.testing.assert_allclose(accel, np.tile([0.0, 0.0, 9.81], (20, 1)), atol=1e-12)


def test_integrating_the_imu_reproduces_the_poses():
    # a manoeuvre: far set-point, then a new one across, with feed-forward
    f1 = fly(hover_state([0.0, 0.0, 2.0], 0.0), [6.0, 4.0, 3.0], 2.0, 600, CFG,
             velocity_ff=[0.5, 0.0, 0.0])
    f2 = fly(f1.state(), [-2.0, 5.0, 2.5], -1.0, 600, CFG)
    p = np.concatenate([f1.p, f2.p[1:]])
    v = np.concatenate([f1.v, f2.v[1:]])
    R = np.concatenate([f1.R_WQ, f2.R_WQ[1:]])
    g1, a1 = imu_samples(f1, CFG.dt)
    g2, a2 = imu_samples(f2, CFG.dt)
    gyro, accel = np.concatenate([g1, g2]), np.concatenate([a1, a2])
    assert np.abs(gyro).max() < 3.0  # continuous attitude: no rate spikes at a command step
    dt = CFG.dt
    Ri, pi, vi = R[0].copy(), p[0].copy(), v[0].copy()
    pos_err = rot_err = 0.0
    for k in range(gyro.shape[0]):
        a_w = Ri @ accel[k] + np.asarray(GRAVITY_W)
        pi = pi + vi * dt + 0.5 * a_w * dt * dt
        vi = vi + a_w * dt
        Ri = Ri @ Rotation.from_rotvec(gyro[k] * dt).as_matrix()
        pos_err = max(pos_err, float(np.linalg.norm(pi - p[k + 1])))
        rot_err = max(rot_err, float(np.linalg.norm(
            Rotation.from_matrix(Ri.T @ R[k + 1]).as_rotvec())))
    assert rot_err < 1e-9
    assert pos_err < 1e-6


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="max_speed"):
        DroneConfig(max_speed=0.0)
