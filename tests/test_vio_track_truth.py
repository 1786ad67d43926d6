"""The front end's matches scored against the truth (uavcal_jax.vio.track_truth): exact
synthetic corners on a fronto-parallel plane, with known errors injected, are scored exactly."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uavcal_jax.data.euroc_rig import (
    EUROC_CAM0_DISTORTION,
    EUROC_CAM0_INTRINSICS,
    EUROC_CAM0_T_BS,
    EUROC_CAM1_DISTORTION,
    EUROC_CAM1_INTRINSICS,
    EUROC_CAM1_T_BS,
)
from uavcal_jax.data.sequence import CameraCalibration, GroundTruth
from uavcal_jax.vio.frontend import FrameFeatures
from uavcal_jax.vio.track_truth import body_poses_at, match_truth

W, H, Z, STEP, N = 752, 480, 3.0, 0.05, 40
LEFT = CameraCalibration(EUROC_CAM0_INTRINSICS, EUROC_CAM0_DISTORTION, (W, H), 20.0,
                         EUROC_CAM0_T_BS)
RIGHT = CameraCalibration(EUROC_CAM1_INTRINSICS, EUROC_CAM1_DISTORTION, (W, H), 20.0,
                          EUROC_CAM1_T_BS)


def _project(P_cam, cal):
    uv, _ = cv2.projectPoints(P_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cal.K,
                              cal.distortion)
    return uv.reshape(-1, 2)


def _normalised(uv, cal):
    return cv2.undistortPoints(uv.reshape(-1, 1, 2), cal.K, cal.distortion, None, None,
                               criteria=(3, 30, 1e-12)).reshape(-1, 2)


@pytest.fixture(scope="module")
def scene():
    """Three frames of a left camera sliding along its own x axis in front of a plane Z m
    away (so the z-depth is Z everywhere), 40 corners, errors injected: 5 px on ids 0-4 in
    frame 2 (temporal), 3 px on the right observations of ids 5-7 in frame 1 (stereo)."""
    rng = np.random.default_rng(0)
    R_BC = EUROC_CAM0_T_BS[:3, :3]
    T_WB = np.tile(np.eye(4), (3, 1, 1))
    T_WB[:, :3, 3] = np.arange(3)[:, None] * STEP * R_BC[:, 0]  # camera x, in the body
    uv0 = rng.uniform([150, 100], [W - 150, H - 100], (N, 2))
    xy0 = _normalised(uv0, LEFT)
    T_WC0 = T_WB[0] @ EUROC_CAM0_T_BS
    P_w = (np.concatenate([xy0, np.ones((N, 1))], 1) * Z) @ T_WC0[:3, :3].T + T_WC0[:3, 3]
    feats = []
    for k in range(3):
        T_CW = np.linalg.inv(T_WB[k] @ EUROC_CAM0_T_BS)
        P_c = P_w @ T_CW[:3, :3].T + T_CW[:3, 3]
        uv = _project(P_c, LEFT)
        T_C1C0 = np.linalg.inv(EUROC_CAM1_T_BS) @ EUROC_CAM0_T_BS
        uv_r = _project(P_c @ T_C1C0[:3, :3].T + T_C1C0[:3, 3], RIGHT)
        if k == 2:
            uv[:5] += [5.0, 0.0]
        if k == 1:
            uv_r[5:8] += [0.0, 3.0]
        feats.append(FrameFeatures(
            t=0.05 * k, ids=np.arange(N), mask=np.ones(N, bool), uv=uv,
            xy=_normalised(uv, LEFT), uv_right=uv_r, xy_right=_normalised(uv_r, RIGHT),
            stereo_mask=np.ones(N, bool), age=np.full(N, k + 1, np.int32)))
    return feats, T_WB


def test_injected_errors_are_the_wrong_matches(scene):
    feats, T_WB = scene
    mt = match_truth(feats, lambda k: np.full((H, W), Z, np.float32), T_WB, LEFT, RIGHT)
    np.testing.assert_array_equal(mt.temporal_n, [0, N, N])
    np.testing.assert_array_equal(mt.temporal_bad, [0, 0, 5])
    np.testing.assert_array_equal(mt.drift_bad, [0, 0, 5])
    # the right observation is scored against the truth behind its left one: a left corner
    # 5 px off (frame 2) makes its exact right match 5 px off too
    np.testing.assert_array_equal(mt.stereo_bad, [0, 3, 5])
    assert mt.temporal_median_px[1] < 0.01 and mt.stereo_median_px[0] < 0.01
    # the exact stereo matches triangulate to the plane's depth
    assert mt.depth_median_rel[0] < 1e-3 and mt.depth_median_rel[2] < 1e-3
    # a 5 cm slide at 3 m moves a corner by about f * 0.05 / 3 pixels
    assert mt.true_flow_median_px[1] == pytest.approx(458.654 * STEP / Z, rel=0.15)
    np.testing.assert_allclose(mt.fraction("stereo"), [0.0, 3 / N, 5 / N])
    assert mt.summary()["temporal_wrong_share"] == pytest.approx(5 / (2 * N))


def test_depth_edges_are_not_scored(scene):
    feats, T_WB = scene
    depth = np.full((H, W), Z, np.float32)
    u, v = np.rint(feats[0].uv[0]).astype(int)
    depth[v, u + 1] = 2 * Z  # an occluding edge beside corner 0 in frame 0
    mt = match_truth(feats, lambda k: depth if k == 0 else np.full((H, W), Z, np.float32),
                     T_WB, LEFT, RIGHT)
    assert mt.stereo_n[0] == N - 1 and mt.temporal_n[1] == N - 1


def test_body_poses_interpolate_the_ground_truth():
    t = np.array([0, 10**9], np.int64)
    gt = GroundTruth(t, np.array([[0.0, 0, 0], [2.0, 0, 0]]),
                     np.array([[1.0, 0, 0, 0], [np.cos(0.5), 0, 0, np.sin(0.5)]]))
    T = body_poses_at(gt, np.array([5 * 10**8]))[0]
    np.testing.assert_allclose(T[:3, 3], [1.0, 0, 0])
    np.testing.assert_allclose(np.arctan2(T[1, 0], T[0, 0]), 0.5, atol=1e-9)
