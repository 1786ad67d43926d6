"""Scene + renderer: depth agrees with the geometry, stereo pairs are epipolar-consistent and
trackable, target boxes are right, scenes are deterministic and keep clear of the path."""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.data import euroc_rig as rig
from uavcal_jax.geometry import camera as C
from uavcal_jax.sim import render as R
from uavcal_jax.sim import scene as S
from uavcal_jax.sim.scene_build import make_scene
from uavcal_jax.sim.target_boxes import target_boxes

# A short, curvy flight path (world z up) inside [-2, 2] x [-2, 2] x [1, 2].
_T = np.linspace(0.0, 2 * np.pi, 200)
PATH = np.stack([2 * np.cos(_T), 1.5 * np.sin(2 * _T), 1.5 + 0.4 * np.sin(3 * _T)], axis=1)


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_WC of a camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


@pytest.fixture(scope="module")
def scene() -> S.Scene:
    return make_scene(PATH.min(0), PATH.max(0), seed=3, path_points=PATH)


def _empty_scene(lo, hi, **kw) -> S.Scene:
    cfg = S.SceneConfig(n_obstacles=0, n_targets=0, **kw)
    return make_scene(lo, hi, seed=0, config=cfg)


def _box_surface_distance(points: np.ndarray, center, yaw, half, inside: bool) -> np.ndarray:
    """Unsigned distance from points to the boundary of a yaw box (float64)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points - np.asarray(center, np.float64)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)
    q = np.abs(local) - np.asarray(half, np.float64)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inner = np.minimum(np.max(q, axis=-1), 0.0)
    return np.abs(outside + inner) if not inside else np.abs(np.max(q, axis=-1))


def _all_boxes(scene, t):
    center, yaw, half = (np.asarray(a, np.float64) for a in S.box_arrays(scene, t))
    return center, yaw, half


def _first_hits(eye, directions, center, yaw, half) -> tuple[np.ndarray, np.ndarray]:
    """Reference ray cast in float64: for rays ``eye + t d`` (``d`` (M, 3) world), the
    parameter ``t`` of the first surface hit and the index of the box hit (0: the hall, seen
    from inside), by the slab test in each yaw box's frame."""
    t_hit = np.full(len(directions), np.inf)
    k_hit = np.zeros(len(directions), np.int64)
    for k in range(len(center)):
        c, s = np.cos(yaw[k]), np.sin(yaw[k])
        rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box axes
        o, d = rot @ (eye - center[k]), directions @ rot.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half[k] - o) / d, (half[k] - o) / d
        t_near = np.max(np.minimum(t1, t2), axis=1)
        t_far = np.min(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0)
        t_k = t_far if k == 0 else np.where(hit, t_near, np.inf)  # the hall: where rays leave
        closer = t_k < t_hit
        t_hit, k_hit = np.where(closer, t_k, t_hit), np.where(closer, k, k_hit)
    return t_hit, k_hit


# --- (b) depth agrees with the geometry --------------------------------------------------------


def test_depth_of_fronto_parallel_wall_is_analytic():
    scn = _empty_scene([0.0, 0.0, 0.0], [4.0, 4.0, 2.0])
    lo, hi = scn.room_lo, scn.room_hi
    cam = rig.euroc_camera(0).scaled(0.25)
    eye = np.array([2.0, 2.0, 1.0])
    T = _look_at(eye, eye + [1.0, 0.0, 0.0])  # optical axis = +x: the wall x = hi[0]
    out = R.render(scn, cam, T, 0.0, color="gray")
    depth = np.asarray(out.depth, np.float64)
    # every ray's exit from the hall, in float64: z-depth = t along the unit-z ray
    rays = np.asarray(R.camera_rays(cam), np.float64).reshape(-1, 3)
    d = rays @ T[:3, :3].T
    with np.errstate(divide="ignore"):
        t_axis = np.where(d > 0, (hi - eye) / d, (lo - eye) / d)
    expected = np.min(np.where(np.isfinite(t_axis), t_axis, np.inf), axis=1).reshape(depth.shape)
    np.testing.assert_allclose(depth, expected, rtol=2e-5)
    # the centre of the image sees the wall 2 + margin metres away, at constant z-depth
    wall = hi[0] - eye[0]
    h, w = depth.shape
    centre = depth[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5]
    np.testing.assert_allclose(centre, wall, rtol=1e-5)
    assert np.all(np.asarray(out.object_id) == -1)


def test_depth_of_floor_looking_down():
    scn = _empty_scene([0.0, 0.0, 0.0], [3.0, 3.0, 2.0])
    cam = rig.euroc_camera(1).scaled(0.25)
    eye = np.array([1.5, 1.5, 1.7])
    T = _look_at(eye, eye + [0.0, 0.0, -1.0])
    depth = np.asarray(R.render(scn, cam, T, color="gray").depth)
    h, w = depth.shape
    floor_distance = eye[2] - scn.room_lo[2]
    np.testing.assert_allclose(depth[h // 2, w // 2], floor_distance, rtol=1e-5)


def test_backprojected_depth_lies_on_scene_surfaces(scene):
    cam = rig.euroc_camera(0).scaled(0.5)
    rng = np.random.default_rng(0)
    rays = np.asarray(R.camera_rays(cam), np.float64)
    target_pixels = reference_target_pixels = 0
    for i in range(6):
        t = 0.7 * i
        eye = PATH[rng.integers(len(PATH))]
        T = _look_at(eye, eye + [*rng.normal(size=2), rng.uniform(-0.6, 0.2)])
        out = R.render(scene, cam, T, t, color="rgb")
        depth = np.asarray(out.depth, np.float64)
        obj = np.asarray(out.object_id)
        assert out.image.shape == (*depth.shape, 3)
        assert np.isfinite(depth).all() and (depth > 0).all()
        pts_cam = rays * depth[..., None]
        pts_w = pts_cam.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        center, yaw, half = _all_boxes(scene, t)
        dist = np.stack(
            [
                _box_surface_distance(pts_w, center[k], yaw[k], half[k], inside=(k == 0))
                for k in range(len(center))
            ],
            axis=1,
        )
        # every pixel's 3D point lies on some face (float32 render: ~1e-6 relative)
        tol = 1e-4 + 2e-5 * depth.reshape(-1)
        assert np.all(dist.min(axis=1) < tol), float(dist.min(axis=1).max())
        # ... and pixels labelled target k lie on target k's box
        n_static = scene.n_static
        for k in np.unique(obj[obj >= 0]):
            m = obj.reshape(-1) == k
            assert np.all(dist[m, n_static + k] < tol[m])
        # a 3D point from pixel u at depth d projects back to u
        idx = rng.integers(0, depth.size, 200)
        pts = jnp.asarray(pts_cam.reshape(-1, 3)[idx])
        uv = np.asarray(C.project(pts, cam.astype(jnp.float32)))
        grid = np.stack(np.meshgrid(np.arange(cam.width), np.arange(cam.height)), -1).reshape(-1, 2)
        np.testing.assert_allclose(uv, grid[idx], atol=1e-2)
        # an independent float64 ray cast of the same boxes sees the same surfaces: the same
        # target (or none) on all but silhouette-edge pixels, at the same depth
        t_ref, k_ref = _first_hits(T[:3, 3], rays.reshape(-1, 3) @ T[:3, :3].T, center, yaw,
                                   half)
        obj_ref = np.where(k_ref >= n_static, k_ref - n_static, -1)
        assert np.mean(obj.reshape(-1) == obj_ref) > 0.999
        rel = np.abs(depth.reshape(-1) - t_ref) / t_ref
        assert np.mean(rel < 1e-4) > 0.999, np.mean(rel < 1e-4)
        target_pixels += int(np.sum(obj >= 0))
        reference_target_pixels += int(np.sum(obj_ref >= 0))
    # the views do see targets, and as many of their pixels as the reference ray cast
    assert reference_target_pixels > 100
    assert abs(target_pixels - reference_target_pixels) <= 1e-3 * reference_target_pixels


# --- (c) stereo: depth transfer, epipolar constraint, trackable texture ------------------------


def _stereo_pair(scene, eye, look, t=0.0, scale=1.0):
    cam0, cam1 = rig.euroc_camera(0).scaled(scale), rig.euroc_camera(1).scaled(scale)
    T_BS0, T_BS1 = rig.EUROC_CAM0_T_BS, rig.EUROC_CAM1_T_BS
    T_WC0 = _look_at(eye, look)
    T_WB = T_WC0 @ np.linalg.inv(T_BS0)
    T_WC1 = T_WB @ T_BS1
    out0 = R.render(scene, cam0, T_WC0, t, color="gray")
    out1 = R.render(scene, cam1, T_WC1, t, color="gray")
    return cam0, cam1, T_WC0, T_WC1, out0, out1


def _essential(T_C1C0: np.ndarray) -> np.ndarray:
    t = T_C1C0[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ T_C1C0[:3, :3]


def test_stereo_depth_transfer_and_epipolar_constraint(scene):
    eye = PATH[10]
    cam0, cam1, T0, T1, out0, out1 = _stereo_pair(scene, eye, eye + [1.0, 0.3, -0.2], scale=0.5)
    T_C1C0 = np.linalg.inv(rig.EUROC_CAM1_T_BS) @ rig.EUROC_CAM0_T_BS
    np.testing.assert_allclose(np.linalg.inv(T1) @ T0, T_C1C0, atol=1e-9)
    d0 = np.asarray(out0.depth, np.float64)
    d1 = np.asarray(out1.depth, np.float64)
    rays0 = np.asarray(R.camera_rays(cam0), np.float64)
    P0 = (rays0 * d0[..., None]).reshape(-1, 3)
    P1 = P0 @ T_C1C0[:3, :3].T + T_C1C0[:3, 3]
    with jax.enable_x64(True):
        cam1_64 = cam1.astype(jnp.float64)
        uv1 = np.asarray(C.project(jnp.asarray(P1), cam1_64))
    H, W = d1.shape
    inside = (uv1[:, 0] > 1) & (uv1[:, 0] < W - 2) & (uv1[:, 1] > 1) & (uv1[:, 1] < H - 2)
    assert inside.mean() > 0.8
    # bilinear sample of cam1's depth at the transferred pixel
    u, v = uv1[inside, 0], uv1[inside, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    sampled = (d1[v0, u0] * (1 - fu) * (1 - fv) + d1[v0, u0 + 1] * fu * (1 - fv)
               + d1[v0 + 1, u0] * (1 - fu) * fv + d1[v0 + 1, u0 + 1] * fu * fv)  # fmt: skip
    rel = np.abs(sampled - P1[inside, 2]) / P1[inside, 2]
    # visible, non-edge points agree to float32 + interpolation precision; occluded or
    # depth-edge ones (a few percent) do not
    assert np.mean(rel < 1e-3) > 0.95, np.mean(rel < 1e-3)
    assert np.median(rel) < 1e-4
    # epipolar constraint of the normalised coordinates
    E = _essential(T_C1C0)
    x0 = rays0.reshape(-1, 3)[inside]
    x1 = P1[inside] / P1[inside, 2:3]
    residual = np.abs(np.einsum("ni,ij,nj->n", x1, E, x0))
    assert residual.max() < 1e-9


def test_stereo_corners_track_along_epipolar_lines(scene):
    """Shi-Tomasi corners of cam0, tracked into cam1 by pyramidal LK, lie on their epipolar
    lines (sub-pixel for most): the texture is trackable and the pair is consistent."""
    eye = PATH[60]
    cam0, cam1, T0, T1, out0, out1 = _stereo_pair(scene, eye, eye + [0.8, -0.6, -0.3])
    img0 = np.asarray(out0.image * 255).round().astype(np.uint8)
    img1 = np.asarray(out1.image * 255).round().astype(np.uint8)
    corners = cv2.goodFeaturesToTrack(img0, maxCorners=400, qualityLevel=0.01, minDistance=12)
    assert corners is not None and len(corners) >= 200  # rich texture
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(
        img0, img1, corners, None, winSize=(21, 21), maxLevel=3
    )
    ok = status[:, 0] == 1
    assert ok.mean() > 0.8
    p0, p1 = corners[ok, 0].astype(np.float64), tracked[ok, 0].astype(np.float64)
    K0, K1 = np.asarray(cam0.K, np.float64), np.asarray(cam1.K, np.float64)
    dist0, dist1 = np.asarray(cam0.distortion, np.float64), np.asarray(cam1.distortion, np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    x0 = cv2.undistortPoints(p0[:, None], K0, dist0, None, None, criteria=crit)[:, 0]
    x1 = cv2.undistortPoints(p1[:, None], K1, dist1, None, None, criteria=crit)[:, 0]
    x0h = np.concatenate([x0, np.ones((len(x0), 1))], 1)
    x1h = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    E = _essential(np.linalg.inv(rig.EUROC_CAM1_T_BS) @ rig.EUROC_CAM0_T_BS)
    lines = x0h @ E.T  # epipolar lines in cam1's normalised plane
    dist_norm = np.abs(np.sum(lines * x1h, 1)) / np.linalg.norm(lines[:, :2], axis=1)
    dist_px = dist_norm * float(cam1.fx)
    assert np.mean(dist_px < 1.0) > 0.85, np.percentile(dist_px, [50, 90])
    assert np.median(dist_px) < 0.3


def test_texture_has_corners_everywhere(scene):
    """Shi-Tomasi (run per cell, as grid-based VIO front ends do) finds corners in every cell
    of a 4x4 grid over the image, near and far, on walls, floor, obstacles and targets."""
    cam = rig.euroc_camera(0)
    eye = PATH[120]
    for look in ([1.0, 0.2, 0.0], [0.0, -1.0, -0.5], [-1.0, 0.5, 0.3]):
        out = R.render(scene, cam, _look_at(eye, eye + look), 0.0, color="gray")
        img = np.asarray(out.image * 255).round().astype(np.uint8)
        H, W = img.shape
        cells = np.zeros((4, 4), int)
        for i in range(4):
            for j in range(4):
                mask = np.zeros_like(img)
                mask[i * H // 4 : (i + 1) * H // 4, j * W // 4 : (j + 1) * W // 4] = 255
                pts = cv2.goodFeaturesToTrack(img, 50, 0.01, 5, mask=mask)
                cells[i, j] = 0 if pts is None else len(pts)
        assert cells.min() >= 10, cells


# --- (d) target boxes ---------------------------------------------------------------------------


def _with_static_targets(scene: S.Scene, xy: np.ndarray, yaw: np.ndarray) -> S.Scene:
    tg = scene.targets
    n = tg.n
    f32 = jnp.float32
    targets = dataclasses.replace(
        tg,
        center=jnp.asarray(xy, f32),
        radii=jnp.zeros((n, 2), f32),
        omega=jnp.zeros((n,), f32),
        yaw=jnp.asarray(yaw, f32),
    )
    return dataclasses.replace(scene, targets=targets)


def test_target_box_contains_projected_centre_and_occlusion(scene):
    assert scene.n_targets >= 2
    cam = rig.euroc_camera(0).scaled(0.5)
    room_c = 0.5 * (scene.room_lo + scene.room_hi)
    # camera low over the floor in the hall's centre, looking along +x
    eye = np.array([room_c[0] - 3.0, room_c[1], scene.room_lo[2] + 1.2])
    T = _look_at(eye, eye + [1.0, 0.0, 0.0])
    n = scene.n_targets
    # target 0 straight ahead 4 m away; target 1 hidden right behind target 0 if it is no
    # larger, else far behind the camera; the others behind the camera
    xy = np.stack([eye[:2] + [4.0 + 6.0 * i, 0.0] if i < 2 else eye[:2] - [3.0, 0.0]
                   for i in range(n)])  # fmt: skip
    xy[2:, 1] += np.arange(n - 2) * 1.5
    scn = _with_static_targets(scene, xy, np.zeros(n))
    half = np.asarray(scn.targets.half_extents)
    hidden = bool(np.all(half[1, 1:] <= half[0, 1:]))
    if not hidden:
        xy[1] = eye[:2] - [3.0, 3.0]
        scn = _with_static_targets(scene, xy, np.zeros(n))
    out = R.render(scn, cam, T, 0.0, color="rgb")
    boxes, visible = (np.asarray(a) for a in target_boxes(out.object_id, n))
    assert boxes.shape == (n, 4) and visible.shape == (n,)
    assert visible[0] > 100
    centre_w = np.array([xy[0, 0], xy[0, 1], float(scn.targets.z[0])])
    centre_c = np.linalg.inv(T) @ np.append(centre_w, 1.0)
    u, v = np.asarray(C.project(jnp.asarray(centre_c[:3], jnp.float32), cam))
    x0, y0, x1, y1 = boxes[0]
    assert x0 <= u < x1 and y0 <= v < y1
    # tight: the box is exactly the extent of the target's pixels
    ys, xs = np.nonzero(np.asarray(out.object_id) == 0)
    np.testing.assert_array_equal(boxes[0], [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
    assert visible[0] == len(xs)
    # hidden (or behind the camera) and behind-the-camera targets: nothing visible, zero box
    assert np.all(visible[1:] == 0)
    assert np.all(boxes[1:] == 0)


def test_target_boxes_batch_and_empty():
    obj = -np.ones((2, 6, 8), np.int32)
    obj[0, 1:3, 2:5] = 1
    obj[1, 5, 7] = 0
    boxes, vis = (np.asarray(a) for a in target_boxes(jnp.asarray(obj), 2))
    np.testing.assert_array_equal(vis, [[0, 6], [1, 0]])
    np.testing.assert_array_equal(boxes[0, 1], [2, 1, 5, 3])
    np.testing.assert_array_equal(boxes[1, 0], [7, 5, 8, 6])
    np.testing.assert_array_equal(boxes[0, 0], [0, 0, 0, 0])


# --- scene construction -------------------------------------------------------------------------


def test_scene_is_deterministic_and_seed_dependent():
    a = make_scene(PATH.min(0), PATH.max(0), seed=5, path_points=PATH)
    b = make_scene(PATH.min(0), PATH.max(0), seed=5, path_points=PATH)
    c = make_scene(PATH.min(0), PATH.max(0), seed=6, path_points=PATH)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not np.array_equal(np.asarray(a.box_center), np.asarray(c.box_center))
    assert S.target_class_names(a) == S.CLASS_NAMES == ("car", "person")


def test_scene_contains_bounds_and_keeps_clear_of_the_path(scene):
    cfg = S.SceneConfig()
    lo, hi = PATH.min(0), PATH.max(0)
    assert np.all(scene.room_lo <= lo - [cfg.margin_xy, cfg.margin_xy, cfg.margin_below] + 1e-5)
    assert np.all(scene.room_hi >= hi + [cfg.margin_xy, cfg.margin_xy, cfg.margin_above] - 1e-5)
    assert scene.n_obstacles >= 4 and scene.n_targets >= 2
    assert set(np.asarray(scene.targets.class_id).tolist()) == {0, 1}
    assert np.any(np.asarray(scene.targets.omega) != 0)  # some targets move
    dense = PATH  # the path points the scene was built from
    for t in np.linspace(0.0, 30.0, 16):
        center, yaw, half = _all_boxes(scene, t)
        for k in range(1, len(center)):
            d = _box_surface_distance(dense, center[k], yaw[k], half[k], inside=False)
            c, s = np.cos(yaw[k]), np.sin(yaw[k])
            rel = dense - center[k]
            local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                              rel[:, 2]], -1)  # fmt: skip
            assert not np.any(np.all(np.abs(local) < half[k], axis=1))  # no point inside
            assert d.min() >= cfg.clearance - 1e-4
        # all solids inside the hall, resting on the floor
        assert np.all(center[1:, 2] - half[1:, 2] >= scene.room_lo[2] - 1e-4)


def test_targets_move_smoothly_on_closed_paths(scene):
    tg = scene.targets
    moving = np.flatnonzero(np.asarray(tg.omega) != 0)
    assert len(moving) > 0
    k = int(moving[0])
    period = 2 * np.pi / abs(float(tg.omega[k]))
    p0 = np.asarray(S.target_poses(scene, 0.3))
    p1 = np.asarray(S.target_poses(scene, 0.3 + period))
    np.testing.assert_allclose(p0[k], p1[k], atol=1e-3)
    # heading follows the velocity; the pose is a rigid transform
    pos, yaw, vel = (np.asarray(a) for a in S.target_states(scene, 1.1))
    heading = np.array([np.cos(yaw[k]), np.sin(yaw[k])])
    np.testing.assert_allclose(heading, vel[k, :2] / np.linalg.norm(vel[k, :2]), atol=1e-5)
    Rm = p0[k, :3, :3]
    np.testing.assert_allclose(Rm @ Rm.T, np.eye(3), atol=1e-6)
    # smooth: small time step -> small displacement
    a = np.asarray(S.target_poses(scene, 2.0))[k, :3, 3]
    b = np.asarray(S.target_poses(scene, 2.01))[k, :3, 3]
    assert np.linalg.norm(a - b) < 0.01 * 3.5
    assert jax.jit(S.target_poses)(scene, 1.0).shape == (scene.n_targets, 4, 4)


def test_scene_without_path_points_keeps_bounds_clear():
    lo, hi = np.array([0.0, 0.0, 1.0]), np.array([3.0, 2.0, 2.0])
    scn = make_scene(lo, hi, seed=1)
    center, yaw, half = _all_boxes(scn, 0.0)
    grid = np.stack(np.meshgrid(*[np.linspace(lo[i], hi[i], 12) for i in range(3)],
                                indexing="ij"), -1).reshape(-1, 3)  # fmt: skip
    for k in range(1, len(center)):
        assert _box_surface_distance(grid, center[k], yaw[k], half[k], False).min() > 0.5


# --- API: batch, jit with a traced camera, colours ----------------------------------------------


def test_render_batch_matches_render_and_traced_camera(scene):
    cam = rig.euroc_camera(0).scaled(0.25)
    eyes = PATH[[5, 50, 95]]
    Ts = np.stack([_look_at(e, e + [1.0, 0.5, -0.2]) for e in eyes])
    ts = np.array([0.0, 0.5, 1.0])
    batch = R.render_batch(scene, cam, Ts, ts, color="gray")
    traced = jax.jit(lambda c, T, t: R.render(scene, c, T, t, color="gray"))
    for i in range(3):
        one = R.render(scene, cam, Ts[i], ts[i], color="gray")
        np.testing.assert_array_equal(np.asarray(batch.image[i]), np.asarray(one.image))
        np.testing.assert_array_equal(np.asarray(batch.depth[i]), np.asarray(one.depth))
        tr = traced(cam, Ts[i], ts[i])  # rays undistorted in the graph, in float32
        np.testing.assert_allclose(np.asarray(tr.depth), np.asarray(one.depth), rtol=1e-4)
        assert np.mean(np.asarray(tr.object_id) == np.asarray(one.object_id)) > 0.999
    assert batch.image.dtype == jnp.float32 and batch.object_id.dtype == jnp.int32
    img = np.asarray(batch.image)
    assert img.min() >= 0.0 and img.max() <= 1.0 and img.std() > 0.05


def test_rgb_and_gray_agree(scene):
    cam = rig.euroc_camera(0).scaled(0.5)
    eye = PATH[30]
    T = _look_at(eye, eye + [1.0, 0.0, -0.3])
    rgb = np.asarray(R.render(scene, cam, T, color="rgb").image)
    gray = np.asarray(R.render(scene, cam, T, color="gray").image)
    # same colours, float32 rounding in a different order (far below one 8-bit level)
    np.testing.assert_allclose(rgb @ np.array([0.299, 0.587, 0.114]), gray, atol=2e-4)
