"""The stereo VIO estimator end to end on the real EuRoC micro slice (against its ground truth),
under bad input (20 black frames, an IMU gap), and its initialisation helpers against
OpenCV and closed forms."""

from __future__ import annotations

import dataclasses
import warnings

import cv2
import numpy as np
import pytest
from conftest import shared_path
from scipy.spatial.transform import Rotation
from vio_frames import frames_ate, process_frames

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.euroc_rig import EUROC_CAM0_T_BS, EUROC_CAM1_T_BS
from uavcal_jax.geometry import so3
from uavcal_jax.vio import ate
from uavcal_jax.vio.initialize import (
    gravity_aligned_rotation,
    gyro_bias_from_rotations,
    level_keeping_heading,
    triangulate_stereo,
    yaw_of,
)
from uavcal_jax.vio.run import run_vio, stereo_pairs


@pytest.fixture(scope="module")
def micro():
    root = shared_path("euroc_v101_micro")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_euroc(root)


@pytest.fixture(scope="module")
def clean_run(micro):
    return run_vio(micro)


def test_micro_slice_ate_within_three_centimetres(micro, clean_run):
    traj = clean_run.trajectory()
    assert len(traj) == len(clean_run.frames) == len(stereo_pairs(micro))
    assert np.all(np.isfinite(traj.position)) and np.all(np.isfinite(traj.quaternion))
    assert clean_run.resets == 0
    result = ate(traj, micro.ground_truth)
    assert result.translation.count == len(traj)
    assert result.translation.rmse <= 0.03
    flags = clean_run.flags()
    assert flags["keyframe"].sum() >= 5  # the hover still makes keyframes (interval rule)
    assert np.all(flags["landmarks"][1:] > 20)
    # the gyro bias is estimated: EuRoC's ground truth has ~0.08 rad/s at this time
    bg_est = clean_run.frames[-1].bias_gyro
    bg_true = micro.ground_truth.bias_gyro[-1]
    assert np.linalg.norm(bg_est - bg_true) < 0.5 * np.linalg.norm(bg_true)


def test_pipelined_and_sequential_runs_are_identical(micro, clean_run):
    # the front end of frame k + 1 is seeded by a bias snapshot taken before update(k) in
    # both modes; before, a pipelined front end read the bias while update(k) wrote it
    seq = run_vio(micro, pipelined=False)
    a, b = clean_run.trajectory(), seq.trajectory()
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.quaternion, b.quaternion)
    np.testing.assert_array_equal(a.bias_gyro, b.bias_gyro)
    assert [f.tracked for f in clean_run.frames] == [f.tracked for f in seq.frames]


def _run_with(micro, black: range = range(0), imu_gap_s: tuple[float, float] | None = None):
    seq = micro
    if imu_gap_s is not None:
        t = (seq.imu.t_ns - seq.camera("cam0").t_ns[0]) * 1e-9
        keep = (t < imu_gap_s[0]) | (t > imu_gap_s[1])
        imu = dataclasses.replace(seq.imu, t_ns=seq.imu.t_ns[keep], gyro=seq.imu.gyro[keep],
                                  accel=seq.imu.accel[keep])
        seq = dataclasses.replace(seq, imu=imu)
    return process_frames(seq, black)


def test_twenty_black_frames_coast_on_the_imu_and_recover(micro):
    frames, vio = _run_with(micro, black=range(30, 50))
    assert all(f.has_pose for f in frames)
    assert all(np.all(np.isfinite(f.position)) for f in frames)
    blind = frames[30:50]
    assert [f.tracked for f in blind] == [0] * 20
    # the window coasts on the IMU once the last landmarks have left it
    assert all(f.status in ("coasting", "reset") for f in blind[10:]), \
        [f.status for f in blind]
    # tracking resumes with new landmarks once the images come back
    assert all(f.status == "tracking" and f.landmarks > 20 for f in frames[55:])
    stats = frames_ate(frames, micro)
    assert stats.max <= 0.10 and stats.rmse <= 0.05


def test_imu_gap_resets_and_continues(micro):
    frames, vio = _run_with(micro, imu_gap_s=(2.0, 2.4))
    gap = [f for f in frames if f.status == "reset"]
    assert gap and all(f.reason == "imu_gap" for f in gap)
    assert vio.resets >= 1
    assert all(f.has_pose and np.all(np.isfinite(f.position)) for f in frames)
    assert frames[-1].status == "tracking"
    stats = frames_ate(frames, micro)
    assert stats.max <= 0.15


def test_stereo_triangulation_matches_opencv():
    rng = np.random.default_rng(0)
    T = np.linalg.inv(EUROC_CAM0_T_BS) @ EUROC_CAM1_T_BS  # cam1 in cam0
    P_left = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-1.5, 1.5, 50),
                              rng.uniform(0.5, 8, 50)])
    P_right = (P_left - T[:3, 3]) @ T[:3, :3]  # X1 = R^T (X0 - t)
    xy0 = P_left[:, :2] / P_left[:, 2:]
    xy1 = P_right[:, :2] / P_right[:, 2:]
    xy0n = xy0 + rng.normal(0, 2e-4, xy0.shape)
    xy1n = xy1 + rng.normal(0, 2e-4, xy1.shape)
    z = triangulate_stereo(xy0n, xy1n, T)
    T10 = np.linalg.inv(T)
    X = cv2.triangulatePoints(np.eye(3, 4), T10[:3], xy0n.T.copy(), xy1n.T.copy())
    z_cv = X[2] / X[3]
    # two least-squares triangulations of the same rays: equal to well within the noise
    np.testing.assert_allclose(z, z_cv, rtol=2e-2)
    np.testing.assert_allclose(triangulate_stereo(xy0, xy1, T), P_left[:, 2], rtol=1e-9)
    # a point behind the rig is not a valid depth
    assert triangulate_stereo(xy0[:1], xy1[:1] + np.array([[0.2, 0.0]]), T)[0] <= 0


def test_gravity_alignment_levels_and_sets_yaw():
    R_true = Rotation.from_euler("zyx", [0.7, 0.1, -0.2]).as_matrix()
    accel = R_true.T @ np.array([0.0, 0.0, 9.81])  # specific force at rest, body frame
    R = gravity_aligned_rotation(accel, yaw=0.3)
    np.testing.assert_allclose(R @ accel, [0.0, 0.0, 9.81], atol=1e-9)
    assert abs(yaw_of(R) - 0.3) < 1e-9
    with pytest.raises(ValueError, match="cannot level"):
        gravity_aligned_rotation(np.zeros(3))


@pytest.mark.parametrize("body_x_up", [True, False])
def test_relevelling_keeps_the_heading_whatever_the_body_convention(body_x_up):
    """A re-initialisation corrects the tilt about a horizontal axis only: the world keeps its
    heading, also for EuRoC's IMU frame (x up), where the body x axis's heading is
    ill-defined and re-levelling at ``yaw_of`` turns the world."""
    # EuRoC's IMU: x up, z forward; FLU: x forward, z up; both turned to heading 0.8 rad
    mount = (Rotation.from_euler("y", -90, degrees=True) if body_x_up else Rotation.identity())
    R_true = (Rotation.from_euler("z", 0.8) * Rotation.from_euler("x", 0.05) * mount).as_matrix()
    tilt_error = Rotation.from_rotvec([0.12, -0.15, 0.0]).as_matrix()  # horizontal axis
    R_ref = tilt_error @ R_true  # the estimate: right heading, 11 degrees of tilt off
    up = R_true.T @ np.array([0.0, 0.0, 9.81])
    R = level_keeping_heading(up, R_ref)
    np.testing.assert_allclose(R @ up, [0.0, 0.0, 9.81], atol=1e-9)
    np.testing.assert_allclose(R, R_true, atol=1e-9)  # the tilt undone, the heading kept
    turned = Rotation.from_matrix(gravity_aligned_rotation(up, yaw_of(R_ref)) @ R_true.T)
    if body_x_up:  # what keeping the body x axis's heading does there
        assert turned.magnitude() > np.radians(5.0)
    with pytest.raises(ValueError, match="cannot level"):
        level_keeping_heading(np.zeros(3), R_ref)


def test_gyro_bias_from_rotations_recovers_a_bias():
    rng = np.random.default_rng(1)
    bias = np.array([0.02, -0.05, 0.08])
    R = [np.eye(3)]
    dR, J = [], []
    for _ in range(8):
        w = rng.normal(0, 0.5, 3)
        dt = 0.2
        step = Rotation.from_rotvec(w * dt).as_matrix()
        R.append(R[-1] @ step)
        # integrated with a zero bias estimate from readings w + bias: the preintegrated
        # rotation is exp((w + bias) dt); its bias Jacobian at constant rate is -Jr(theta) dt
        theta = (w + bias) * dt
        dR.append(Rotation.from_rotvec(theta).as_matrix())
        J.append(-dt * np.asarray(so3.right_jacobian(theta)))
    d = gyro_bias_from_rotations(np.stack(R), np.stack(dR), np.stack(J))
    # one Gauss-Newton step from zero: exact to second order in the bias
    np.testing.assert_allclose(d, bias, atol=2e-4)
