"""Camera model: agreement with OpenCV, distortion round trips, rays, calibration plumbing."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.data import euroc_rig as rig
from uavcal_jax.geometry import camera as C


def _points_in_view(cam_index: int, n: int, seed: int) -> np.ndarray:
    """Random camera-frame points whose projections fall inside the EuRoC image."""
    rng = np.random.default_rng(seed)
    intr = (rig.EUROC_CAM0_INTRINSICS, rig.EUROC_CAM1_INTRINSICS)[cam_index]
    dist = (rig.EUROC_CAM0_DISTORTION, rig.EUROC_CAM1_DISTORTION)[cam_index]
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    uv = rng.uniform([0, 0], [752, 480], size=(n, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    xy = cv2.undistortPoints(uv[:, None], K, dist, None, None, criteria=crit)[:, 0]
    depth = rng.uniform(0.2, 30.0, size=(n, 1))
    return np.concatenate([xy, np.ones((n, 1))], axis=1) * depth


def _cv2_project(points: np.ndarray, cam: C.PinholeRadtan) -> np.ndarray:
    K = np.asarray(cam.K, dtype=np.float64)
    dist = np.asarray(cam.distortion, dtype=np.float64)
    out, _ = cv2.projectPoints(points.astype(np.float64), np.zeros(3), np.zeros(3), K, dist)
    return out[:, 0]


@pytest.mark.parametrize("cam_index", [0, 1])
def test_project_matches_opencv_float64(x64, cam_index):
    cam = rig.euroc_camera(cam_index)
    assert cam.fx.dtype == jnp.float64
    pts = _points_in_view(cam_index, 5000, seed=cam_index)
    ours = np.asarray(jax.jit(C.project)(jnp.asarray(pts), cam))
    ref = _cv2_project(pts, cam)
    assert np.abs(ours - ref).max() < 1e-3
    assert np.abs(ours - ref).max() < 1e-8  # in fact exact to rounding


def test_project_matches_opencv_random_lens(x64):
    rng = np.random.default_rng(3)
    for _ in range(5):
        intr = [
            rng.uniform(200, 800),
            rng.uniform(200, 800),
            rng.uniform(200, 400),
            rng.uniform(150, 300),
        ]
        dist = [
            rng.uniform(-0.3, 0.1),
            rng.uniform(-0.05, 0.1),
            rng.uniform(-1e-3, 1e-3),
            rng.uniform(-1e-3, 1e-3),
        ]
        cam = C.PinholeRadtan.create(intr, dist, (640, 480))
        pts = np.concatenate([rng.uniform(-0.6, 0.6, (500, 2)), np.ones((500, 1))], 1)
        pts = pts * rng.uniform(0.5, 10.0, (500, 1))
        assert np.abs(np.asarray(C.project(pts, cam)) - _cv2_project(pts, cam)).max() < 1e-3


def test_project_float32_tolerance():
    """float32: ~1e-7 relative rounding on pixel coordinates of a few hundred px; we document
    and check 2e-3 px."""
    cam = rig.euroc_camera(0, dtype=jnp.float32)
    assert cam.fx.dtype == jnp.float32
    pts = _points_in_view(0, 5000, seed=7)
    ours = np.asarray(C.project(jnp.asarray(pts, jnp.float32), cam), dtype=np.float64)
    ref = _cv2_project(pts, rig.euroc_camera(0, dtype=jnp.float32))
    assert np.abs(ours - ref).max() < 2e-3


def test_undistort_inverts_distort(x64):
    cam = rig.euroc_camera(0)
    rng = np.random.default_rng(1)
    # The whole image in normalised coordinates, corners included (|x| up to ~1.3).
    xy = jnp.asarray(rng.uniform([-1.4, -0.9], [1.4, 0.9], size=(20000, 2)))
    back = C.undistort_normalized(C.distort(xy, cam), cam)
    assert float(jnp.abs(back - xy).max()) < 1e-12
    # and the other way round, from distorted coordinates of every image pixel
    xyd = (C.pixel_grid(cam).reshape(-1, 2) - cam.intrinsics[2:]) / cam.intrinsics[:2]
    assert float(jnp.abs(C.distort(C.undistort_normalized(xyd, cam), cam) - xyd).max()) < 1e-12


def test_undistort_matches_opencv(x64):
    cam = rig.euroc_camera(1)
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [752, 480], size=(2000, 2))
    ours = np.asarray(C.pixels_to_normalized(jnp.asarray(uv), cam))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    ref = cv2.undistortPoints(
        uv[:, None], np.asarray(cam.K), np.asarray(cam.distortion), None, None, criteria=crit
    )[:, 0]
    assert np.abs(ours - ref).max() < 1e-8


def test_undistort_float32():
    cam = rig.euroc_camera(0, dtype=jnp.float32)
    xy = jnp.asarray(np.random.default_rng(4).uniform(-1.3, 1.3, (1000, 2)), jnp.float32)
    back = C.undistort_normalized(C.distort(xy, cam), cam)
    assert float(jnp.abs(back - xy).max()) < 2e-6


def test_pixel_rays_reproject_to_pixel_centres(x64):
    cam = rig.euroc_camera(0)
    rays = C.pixel_rays(cam)
    assert rays.shape == (480, 752, 3)
    np.testing.assert_allclose(np.asarray(rays[..., 2]), 1.0)
    uv = C.project(rays * 3.7, cam)
    assert float(jnp.abs(uv - C.pixel_grid(cam)).max()) < 1e-9
    assert float(uv[5, 11, 0]) == pytest.approx(11.0) and float(uv[5, 11, 1]) == pytest.approx(5.0)


def test_unproject_with_depth_round_trip(x64):
    cam = rig.euroc_camera(1)
    uv = jnp.asarray(np.random.default_rng(5).uniform([0, 0], [751, 479], (100, 2)))
    d = jnp.linspace(0.3, 40.0, 100)
    p = C.unproject(uv, cam, d)
    np.testing.assert_allclose(np.asarray(p[:, 2]), np.asarray(d))
    np.testing.assert_allclose(np.asarray(C.project(p, cam)), np.asarray(uv), atol=1e-9)


def test_from_calibration_and_euroc_constants(euroc_micro):
    from uavcal_jax.data import camera_calibration_from_yaml, read_sensor_yaml

    for i in (0, 1):
        path = euroc_micro / "mav0" / f"cam{i}" / "sensor.yaml"
        calib = camera_calibration_from_yaml(read_sensor_yaml(path), path)
        cam = C.from_calibration(calib)
        ours = rig.euroc_calibration(i)
        np.testing.assert_allclose(ours.intrinsics, calib.intrinsics)
        np.testing.assert_allclose(ours.distortion, calib.distortion)
        np.testing.assert_allclose(ours.T_BS, calib.T_BS)
        assert tuple(ours.resolution) == tuple(calib.resolution) == (752, 480)
        assert ours.rate_hz == pytest.approx(calib.rate_hz)
        assert (cam.width, cam.height) == (752, 480)
        np.testing.assert_allclose(np.asarray(cam.intrinsics), calib.intrinsics, rtol=1e-6)


def test_camera_is_a_pytree_with_static_size():
    cam = rig.euroc_camera(0)
    leaves, treedef = jax.tree_util.tree_flatten(cam)
    assert len(leaves) == 8
    cam2 = jax.tree_util.tree_unflatten(treedef, leaves)
    assert (cam2.width, cam2.height) == (752, 480)

    @jax.jit
    def f(c, p):
        return C.project(p, c)

    p = jnp.array([[0.1, -0.2, 2.0]], dtype=jnp.float32)
    a = f(cam, p)
    b = f(rig.euroc_camera(1), p)  # same shapes: no retrace needed, different values
    assert not np.allclose(np.asarray(a), np.asarray(b))


def test_scaled_keeps_field_of_view(x64):
    cam = rig.euroc_camera(0)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (376, 240)
    p = jnp.array([0.3, -0.2, 1.0])
    uv, uv_half = C.project(p, cam), C.project(p, half)
    np.testing.assert_allclose(np.asarray(uv_half), (np.asarray(uv) + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_euroc_stereo_baseline():
    T = np.linalg.inv(rig.EUROC_CAM0_T_BS) @ rig.EUROC_CAM1_T_BS  # cam1 in cam0
    # cam1 sits ~11 cm to the right of cam0 (x axis), nearly parallel.
    assert 0.10 < T[0, 3] < 0.12
    assert np.abs(T[:3, :3] - np.eye(3)).max() < 0.02
