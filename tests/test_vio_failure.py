"""Failure detection (uavcal_jax.vio.failure: the velocity jump against the IMU prediction,
the window's chi-square test) and the re-initialisation while moving that follows a reset
(uavcal_jax.vio.motion_init): gravity and velocity from stereo odometry and the IMU on an
accelerating, turning synthetic flight, where levelling by the accelerometer mean would be
over 10 degrees off."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc_rig import EUROC_CAM0_T_BS, EUROC_CAM1_T_BS
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import FailureLimits
from uavcal_jax.vio.failure import Failure, check_failure, chi2_bound, cost_excess_frames
from uavcal_jax.vio.frontend import FrameFeatures
from uavcal_jax.vio.initialize import gravity_aligned_rotation
from uavcal_jax.vio.motion_init import initialize_moving

A_W = np.array([3.0, 0.0, 1.0])  # m/s^2, world acceleration
V0 = np.array([2.0, 0.5, 0.0])  # m/s
RATE = 0.3  # rad/s about world z
R0 = Rotation.from_euler("x", 0.2).as_matrix()
FRAMES, DT, SUB = 10, 0.05, 10


def _pose(t):
    R = Rotation.from_euler("z", RATE * t).as_matrix() @ R0
    return R, V0 * t + 0.5 * A_W * t * t, V0 + A_W * t


def _features(P_w, t, k):
    R, p, _ = _pose(t)
    T_WC = np.eye(4)
    T_WC[:3, :3], T_WC[:3, 3] = R, p
    T_WC = T_WC @ EUROC_CAM0_T_BS
    T_CW = np.linalg.inv(T_WC)
    P0 = P_w @ T_CW[:3, :3].T + T_CW[:3, 3]
    T_C1C0 = np.linalg.inv(EUROC_CAM1_T_BS) @ EUROC_CAM0_T_BS
    P1 = P0 @ T_C1C0[:3, :3].T + T_C1C0[:3, 3]
    xy0, xy1 = P0[:, :2] / P0[:, 2:], P1[:, :2] / P1[:, 2:]
    vis = (P0[:, 2] > 0.5) & np.all(np.abs(xy0) < 0.8, 1)
    n = len(P_w)
    feats = FrameFeatures(t, np.arange(n), vis, xy0 * 458 + 370, xy0, xy1 * 458 + 370, xy1,
                          vis, np.full(n, k + 1, np.int32))
    return feats, (np.where(vis, P0[:, 2], 0.0), vis)


@pytest.fixture(scope="module")
def stretch():
    rng = np.random.default_rng(1)
    R, p, _ = _pose(0.0)
    axis = R @ EUROC_CAM0_T_BS[:3, 2]  # the optical axis at the start
    side = np.cross(axis, [0, 0, 1.0])
    side /= np.linalg.norm(side)
    up = np.cross(side, axis)
    P_w = (p + rng.uniform(4, 8, (150, 1)) * axis + rng.uniform(-3, 3, (150, 1)) * side
           + rng.uniform(-2, 2, (150, 1)) * up)
    frames = [_features(P_w, k * DT, k) for k in range(FRAMES)]
    rows = []
    g = np.asarray(GRAVITY_W, np.float64)
    for k in range(FRAMES - 1):
        t = k * DT + (np.arange(SUB) + 0.5) * DT / SUB  # sample midpoints
        gyro = np.tile(R0.T @ [0, 0, RATE], (SUB, 1))  # constant body rate
        accel = np.stack([_pose(s)[0].T @ (A_W - g) for s in t])
        rows.append((np.full(SUB, DT / SUB), gyro, accel))
    return frames, rows


def test_moving_start_recovers_tilt_and_velocity(stretch):
    frames, rows = stretch
    R_true, _, v_true = _pose((FRAMES - 1) * DT)
    init = initialize_moving([f for f, _ in frames], [d for _, d in frames], rows,
                             EUROC_CAM0_T_BS, R_true)
    assert init is not None
    tilt = np.degrees(np.arccos(np.clip(init.rotation[2] @ R_true[2], -1, 1)))
    assert tilt < 0.5
    # with the true rotation as the reference, its heading is kept: the whole rotation
    assert np.degrees(Rotation.from_matrix(init.rotation @ R_true.T).magnitude()) < 0.5
    np.testing.assert_allclose(init.velocity, v_true, atol=0.05)
    assert init.gravity_norm == pytest.approx(9.81, abs=0.2)
    # what levelling by the accelerometer would have done here
    level = gravity_aligned_rotation(rows[-1][2].mean(0))
    assert np.degrees(np.arccos(np.clip(level[2] @ R_true[2], -1, 1))) > 10


def test_lost_odometry_gives_no_start(stretch):
    frames, rows = stretch
    feats = [f for f, _ in frames]
    depths = [d for _, d in frames]
    # frame 5 shares no corner with frame 4 (new ids): the odometry breaks
    f5 = feats[5]
    feats[5] = FrameFeatures(f5.t, f5.ids + 1000, f5.mask, f5.uv, f5.xy, f5.uv_right,
                             f5.xy_right, f5.stereo_mask, f5.age)
    assert initialize_moving(feats, depths, rows, EUROC_CAM0_T_BS) is None


def _state(velocity=(5.0, 0.0, 0.0)):
    return BodyState(0, np.eye(3), np.zeros(3), np.asarray(velocity, float), np.zeros(3),
                     np.zeros(3))


def test_chi2_counts_consecutive_inconsistent_windows():
    lim = FailureLimits()
    assert chi2_bound(1000, lim) == pytest.approx(lim.chi2_scale * (1000 + lim.chi2_z
                                                                    * np.sqrt(2000)))
    n = 0
    for cost in (100.0, 900.0, 900.0, 100.0, 900.0):  # 2 cost against ~1139 for 1000 rows
        n = cost_excess_frames(n, cost, 1000, lim)
    assert n == 1


def test_failure_checks_fire_on_velocity_jump_and_lasting_chi2():
    lim = FailureLimits(max_cost_frames=10)
    pred = _state()
    assert check_failure(_state(), pred, 100.0, 1000, 0, lim) is None
    jumped = _state((5.0, lim.max_velocity_jump + 0.1, 0.0))
    assert check_failure(jumped, pred, 100.0, 1000, 0, lim) is Failure.VELOCITY
    assert check_failure(jumped, pred, 100.0, 1000, 0, lim, velocity_check=False) is None
    assert check_failure(_state(), pred, 900.0, 1000, 0, lim,
                         cost_excess=lim.max_cost_frames) is None
    assert check_failure(_state(), pred, 900.0, 1000, 0, lim,
                         cost_excess=lim.max_cost_frames + 1) is Failure.CHI2
    off = FailureLimits(max_cost_frames=0)  # the default: the test is off
    assert check_failure(_state(), pred, 900.0, 1000, 0, off, cost_excess=99) is None
