"""track.locate / track.stereo: a box + depth (or a stereo pair) + the pose -> the target's world
centre, against ground truth from synthetic renders of a target patch in front of a farther
background, with holes (the centre pixel among them)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.data import euroc_rig as rig
from uavcal_jax.geometry import camera as C
from uavcal_jax.track import box_model as BM
from uavcal_jax.track import locate as L
from uavcal_jax.track import stereo as S

EXTENT = 0.6  # the target's depth extent, metres
HALF = 0.35  # half-size of its front face, metres
BACKGROUND = 9.0  # metres along the camera's z


def _pose(yaw: float, position) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = position
    return T


def _patch_frame(centre_C: np.ndarray):
    """Front face of the target: centre, normal (the ray to the centre) and two in-plane axes.
    The target's centre lies EXTENT/2 behind the face along the ray, as locate assumes."""
    ray = centre_C / np.linalg.norm(centre_C)
    e1 = np.cross([0.0, 1.0, 0.0], ray)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ray, e1)
    return centre_C - 0.5 * EXTENT * ray, ray, e1, e2


_RAYS: dict[tuple, np.ndarray] = {}


def _rays(cam: C.PinholeRadtan) -> np.ndarray:
    """(H, W, 3) unit-z pixel rays, computed once per lens."""
    key = (cam.resolution, *(float(v) for v in cam.intrinsics), *(float(v) for v in cam.distortion))
    if key not in _RAYS:
        _RAYS[key] = np.asarray(jax.jit(C.pixel_rays)(cam), np.float64)
    return _RAYS[key]


def _render_depth(cam: C.PinholeRadtan, centre_C: np.ndarray, hole_fraction=0.25, seed=0):
    """(H, W) z-depth: the target's front face in front of a fronto-parallel background at
    BACKGROUND m, with random holes (0) and a hole at the box centre; and the tight box
    (inclusive-exclusive pixel edges, as the simulator labels)."""
    rays = _rays(cam)  # (H, W, 3) unit-z
    p0, n, e1, e2 = _patch_frame(centre_C)
    t = (p0 @ n) / (rays @ n)
    q = t[..., None] * rays - p0
    on = (np.abs(q @ e1) <= HALF) & (np.abs(q @ e2) <= HALF) & (t > 0)
    depth = np.where(on, t, BACKGROUND)
    rows, cols = np.nonzero(on)
    box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], np.float64)
    rng = np.random.default_rng(seed)
    depth[rng.random(depth.shape) < hole_fraction] = 0.0
    cu, cv = int((box[0] + box[2]) / 2), int((box[1] + box[3]) / 2)
    depth[cv - 2:cv + 3, cu - 2:cu + 3] = 0.0  # the centre pixel is a hole
    return depth.astype(np.float32), box


@pytest.fixture(scope="module")
def cam() -> C.PinholeRadtan:
    return rig.euroc_camera(0).scaled(0.25)  # 188 x 120, EuRoC's distortion


@pytest.fixture(scope="module")
def setup():
    T_BC = rig.EUROC_CAM0_T_BS
    T_WB = _pose(0.7, [1.0, -2.0, 1.5])
    return T_BC, T_WB, T_WB @ T_BC


def _world(T, p):
    return T[:3, :3] @ p + T[:3, 3]


@pytest.mark.parametrize("centre_C", [(0.0, 0.0, 4.0), (-0.9, 0.4, 3.0), (0.8, -0.5, 6.0)])
def test_located_point_matches_the_true_centre(cam, setup, centre_C):
    T_BC, T_WB, T_WC = setup
    centre_C = np.asarray(centre_C)
    depth, box = _render_depth(cam, centre_C)
    cu, cv = int((box[0] + box[2]) / 2), int((box[1] + box[3]) / 2)
    assert depth[cv, cu] == 0.0  # a centre-pixel reader would see nothing here
    out = L.locate_box(box, depth, cam, T_BC, T_WB, extent=EXTENT)
    assert bool(out.located) and int(out.reason) == L.LOCATED
    err = np.linalg.norm(np.asarray(out.point) - _world(T_WC, centre_C))
    assert err < 0.04, err
    # without the front-surface correction the point sits ~EXTENT/2 short of the centre
    short = L.locate_box(box, depth, cam, T_BC, T_WB, extent=0.0)
    assert np.linalg.norm(np.asarray(short.point) - _world(T_WC, centre_C)) > 0.25
    cov = np.asarray(out.covariance)
    assert np.allclose(cov, cov.T, atol=1e-9) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_no_depth_is_not_located_never_the_origin(cam, setup):
    T_BC, T_WB, _ = setup
    depth, box = _render_depth(cam, np.array([0.0, 0.0, 4.0]))
    for bad in (np.zeros_like(depth), np.full_like(depth, np.nan)):
        out = L.locate_box(box, bad, cam, T_BC, T_WB)
        assert not bool(out.located) and int(out.reason) == L.NO_DEPTH
        assert np.all(np.isnan(np.asarray(out.point)))
    outside = L.locate_box(np.array([500.0, 500.0, 520.0, 530.0]), depth, cam, T_BC, T_WB)
    assert int(outside.reason) == L.OUTSIDE_IMAGE and not bool(outside.located)
    empty = L.locate_box(np.array([50.0, 50.0, 50.0, 60.0]), depth, cam, T_BC, T_WB)
    assert int(empty.reason) == L.OUTSIDE_IMAGE


def test_robust_depth_rejects_background_and_specks():
    rng = np.random.default_rng(1)
    values = np.concatenate([4.0 + 0.01 * rng.standard_normal(60),  # the target
                             np.full(30, 12.0), np.zeros(20), [0.5, 0.6]])  # bg, holes, specks
    out = L.robust_depth(jnp.asarray(values))
    assert int(out.reason) == L.LOCATED and abs(float(out.depth) - 4.0) < 0.01
    scattered = L.robust_depth(jnp.linspace(1.0, 30.0, 100), L.LocateConfig(min_inliers=0.3))
    assert int(scattered.reason) == L.NO_CONSISTENT_SURFACE


def test_covariance_on_the_optical_axis_is_the_stereo_model(x64):
    # no distortion, the principal point: cov_C = diag(((z + e/2) s_px / f)^2 (x, y), s_z^2)
    cam = C.PinholeRadtan.create((200.0, 180.0, 80.0, 50.0), (0.0,) * 4, (160, 100))
    cfg = L.LocateConfig(pixel_sigma=1.5, disparity_sigma=0.3, baseline=0.12,
                         depth_sigma_min=0.0)
    z, e = 5.0, 0.4
    R_WC = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    T_WC = np.eye(4)
    T_WC[:3, :3], T_WC[:3, 3] = R_WC, [1.0, 2.0, 3.0]
    measured = L.BoxDepth(jnp.asarray(z), jnp.asarray(L.LOCATED), 1.0, 1.0)
    out = L.locate_from_depth(jnp.array([80.0, 50.0]), measured, cam, jnp.asarray(T_WC), e, cfg)
    s_z = z * z * 0.3 / (200.0 * 0.12)
    cov_C = np.diag([((z + e / 2) * 1.5 / 200.0) ** 2, ((z + e / 2) * 1.5 / 180.0) ** 2, s_z ** 2])
    np.testing.assert_allclose(np.asarray(out.covariance), R_WC @ cov_C @ R_WC.T,
                               rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(out.point), R_WC @ [0, 0, z + e / 2] + [1, 2, 3],
                               atol=1e-12)


def test_locate_jits_and_vmaps_over_boxes(cam, setup):
    T_BC, T_WB, T_WC = setup
    centre_C = np.array([0.0, 0.0, 4.0])
    depth, box = _render_depth(cam, centre_C)
    boxes = jnp.stack([jnp.asarray(box), jnp.array([500.0, 500.0, 510.0, 510.0])])
    f = jax.jit(jax.vmap(lambda b: L.locate_box(b, depth, cam, T_BC, T_WB, extent=EXTENT)))
    out = f(boxes)
    assert np.asarray(out.located).tolist() == [True, False]
    assert np.linalg.norm(np.asarray(out.point[0]) - _world(T_WC, centre_C)) < 0.04


# --- the stereo path ------------------------------------------------------------------------


def _texture(seed: int, size=512) -> np.ndarray:
    noise = np.random.default_rng(seed).random((size, size)).astype(np.float32)
    noise = cv2.GaussianBlur(noise, (0, 0), 1.5)
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    return noise * 255.0


def _render_grey(cam, T_WC, centre_W, n_W, e1_W, e2_W, tex_target, tex_bg, bg_plane):
    """(H, W) uint8: the textured front face of the target (texels of 1 cm) over a textured
    background plane (texels of 3 cm), both planes in world coordinates."""
    rays = _rays(cam) @ T_WC[:3, :3].T  # world directions
    origin = T_WC[:3, 3]

    def hit(p0, n, a1, a2, half, texel, tex):
        t = ((p0 - origin) @ n) / (rays @ n)
        q = origin + t[..., None] * rays - p0
        u, v = q @ a1, q @ a2
        inside = (t > 0) & (np.abs(u) <= half) & (np.abs(v) <= half)
        size = tex.shape[0]
        mx = np.mod(u / texel + size / 2, size - 1).astype(np.float32)
        my = np.mod(v / texel + size / 2, size - 1).astype(np.float32)
        value = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
        return np.where(inside, t, np.inf), value

    t_target, v_target = hit(centre_W, n_W, e1_W, e2_W, HALF, 0.01, tex_target)
    t_bg, v_bg = hit(*bg_plane, np.inf, 0.03, tex_bg)
    return np.clip(np.where(t_target < t_bg, v_target, v_bg), 0, 255).astype(np.uint8)


def test_stereo_locates_the_target_in_a_synthetic_pair(setup):
    T_BC0, T_WB, _ = setup
    T_BC1 = rig.EUROC_CAM1_T_BS
    cam0, cam1 = rig.euroc_camera(0).scaled(0.5), rig.euroc_camera(1).scaled(0.5)  # 376 x 240
    T_WC0, T_WC1 = T_WB @ T_BC0, T_WB @ T_BC1
    centre_C = np.array([0.3, -0.1, 1.8])  # in the left camera
    p0_C, n_C, e1_C, e2_C = _patch_frame(centre_C)
    R = T_WC0[:3, :3]
    face = (_world(T_WC0, p0_C), R @ n_C, R @ e1_C, R @ e2_C)
    bg_n = R @ np.array([0.0, 0.0, 1.0])
    bg = (_world(T_WC0, np.array([0.0, 0.0, BACKGROUND])), bg_n,
          R @ np.array([1.0, 0.0, 0.0]), R @ np.array([0.0, 1.0, 0.0]))
    tex_t, tex_b = _texture(1), _texture(2)
    left = _render_grey(cam0, T_WC0, *face, tex_t, tex_b, bg)
    right = _render_grey(cam1, T_WC1, *face, tex_t, tex_b, bg)
    depth, box = _render_depth(cam0, centre_C, hole_fraction=0.0)  # only for the true box

    rect = S.rectify_stereo(cam0, cam1, T_BC0, T_BC1)
    baseline = np.linalg.norm(rig.EUROC_CAM1_T_BS[:3, 3] - rig.EUROC_CAM0_T_BS[:3, 3])
    assert abs(rect.baseline - baseline) < 1e-6
    out = S.locate_box_stereo(box, left, right, rect, T_BC0, T_WB, extent=EXTENT)
    assert bool(out.located), L.REASONS[int(out.reason)]
    err = np.asarray(out.point) - _world(T_WC0, centre_C)
    sigma = np.sqrt(np.linalg.eigvalsh(np.asarray(out.covariance)).max())
    assert np.linalg.norm(err) < 0.06, (err, sigma)
    # the point's error is inside its own 3-sigma ellipsoid
    d2 = err @ np.linalg.solve(np.asarray(out.covariance, np.float64), err)
    assert d2 < 3.0 ** 2 * 3, d2
    # an untextured (unmatched) pair gives no point
    blank = np.full_like(left, 128)
    assert not bool(S.locate_box_stereo(box, blank, blank, rect, T_BC0, T_WB).located)


# -- the box model: front surface -> centre ------------------------------------------------


def test_heading_from_velocity_is_unknown_when_slow():
    from uavcal_jax.track.heading import heading_from_velocity

    v = np.array([[np.nan] * 3, [0.1, 0.0, 0], [0.0, 2.0, 0], [0.1, 0.1, 0], [-3.0, 0.0, 0]])
    yaw = heading_from_velocity(v, min_speed=0.5)
    assert np.isnan(yaw[[0, 1, 3]]).all()
    np.testing.assert_allclose(yaw[[2, 4]], [np.pi / 2, np.pi])


def _render_box_depth(cam, T_WC, centre_W, half, yaw):
    """(H, W) z-depth of a yawed box (ray-cast, slab method) before a far background."""
    rays_C = _rays(cam).reshape(-1, 3)  # unit z
    R = Rotation.from_euler("z", yaw).as_matrix()
    d = rays_C @ (R.T @ T_WC[:3, :3]).T  # ray directions in the box frame
    o = R.T @ (T_WC[:3, 3] - centre_W)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (near <= far) & (near > 0)
    depth = np.where(hit, near, BACKGROUND * 3).reshape(cam.resolution[1], cam.resolution[0])
    rows, cols = np.nonzero(hit.reshape(depth.shape))
    box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], np.float64)
    return depth.astype(np.float32), box


def _look_at(cam_pos, target) -> np.ndarray:
    """(4, 4) camera-to-world pose at ``cam_pos`` looking at ``target`` (x right, y down)."""
    forward = target - cam_pos
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T_WC = np.eye(4)
    T_WC[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    T_WC[:3, 3] = cam_pos
    return T_WC


CAR_HALF = np.array([2.1, 0.875, 0.725])


@pytest.mark.parametrize("k", [0, 2, 4, 6, 8, 10, 13])  # yaw 0, 0.39, ..., 2.55 rad
@pytest.mark.parametrize("height, distance", [(2.0, 6.0), (5.0, 8.0)])
def test_box_centre_recovers_a_car_centre_from_any_side(k, height, distance):
    """A car-sized box on the floor, ray-cast at seven headings from two drone heights: the
    box model puts the located front surface within 0.12 m of the centre with the heading
    known; with the heading chosen from the box's shape within 0.9 m, and never worse than
    the old constant half-extent of 1.25 m along the ray plus 0.05 m."""
    yaw = BM.CANDIDATE_HEADINGS[k]
    cam = rig.euroc_camera(0).scaled(0.5)
    centre = np.array([distance, 0.5, CAR_HALF[2]])
    cam_pos = np.array([0.0, 0.0, height])
    T_WC = _look_at(cam_pos, centre)
    depth, box = _render_box_depth(cam, T_WC, centre, CAR_HALF, yaw)
    config = L.LocateConfig(quantile=0.5)
    front = L.locate_box(box, depth, cam, np.eye(4), T_WC, 0.0, config)
    assert bool(front.located)
    p = np.asarray(front.point)
    centres, mismatch = BM.box_centre_candidates(p, T_WC, CAR_HALF, box, cam, config)
    known = np.asarray(centres)[k]  # the true heading's candidate
    shape = np.asarray(centres)[int(np.argmin(mismatch))]  # the best-fitting shape
    ray = (p - cam_pos) / np.linalg.norm(p - cam_pos)
    constant = p + 1.25 * ray
    assert np.linalg.norm(known - centre) < 0.12
    assert np.linalg.norm(shape - centre) < min(0.9, np.linalg.norm(constant - centre) + 0.05)


def test_heading_tracker_resolves_the_mirror_ambiguity_with_the_velocity():
    """Two mirror headings fit every box equally; a noisy velocity pointing near one of them
    settles the tracker on it, and it holds that heading through frames without velocity."""
    from uavcal_jax.track.heading import track_heading

    grid = BM.CANDIDATE_HEADINGS
    true_index, mirror_index = 3, 11
    mismatch = np.full((40, grid.size), 0.05)
    mismatch[:, [true_index, mirror_index]] = 0.0
    rng = np.random.default_rng(0)
    velocity = grid[true_index] + rng.normal(0.0, 0.4, 40)
    velocity[25:] = np.nan  # the target stops
    chosen, _ = track_heading(np.arange(40) * 0.05, mismatch, velocity)
    assert np.all(chosen[5:] == true_index)
    shape_only, _ = track_heading(np.arange(40) * 0.05, mismatch, np.full(40, np.nan))
    assert set(shape_only) <= {true_index, mirror_index}


def test_heading_spread_is_the_belief_weighted_scatter_about_the_chosen_centre():
    from uavcal_jax.track.heading import heading_spread

    centres = np.zeros((2, 4, 3))
    centres[0, 1] = [1.0, 0.0, 0.0]
    centres[1, :, 1] = [0.0, 0.5, 0.0, 0.0]
    belief = np.array([[0.5, 0.5, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    spread = heading_spread(centres, belief, np.array([0, 0]))
    np.testing.assert_allclose(spread[0], np.diag([0.5, 0.0, 0.0]))
    np.testing.assert_allclose(spread[1], 0.0)


def test_box_centre_locates_a_car_cut_by_the_image_border():
    """The same car, the camera turned so that its box runs off the image's left edge: the
    model's box is cut there too, and the centre is found about as well as whole (the lens
    distortion near the edge costs a little); the constant half-extent is twice as far off."""
    cam = rig.euroc_camera(0).scaled(0.5)
    centre = np.array([6.0, 0.5, CAR_HALF[2]])
    cam_pos = np.array([0.0, 0.0, 2.0])
    T_WC = _look_at(cam_pos, centre + np.array([0.0, -5.5, 0.0]))  # the car sits off to the left
    k = 2  # the heading, yaw 0.39 rad
    depth, box = _render_box_depth(cam, T_WC, centre, CAR_HALF, BM.CANDIDATE_HEADINGS[k])
    assert box[0] == 0.0  # cut by the border
    config = L.LocateConfig(quantile=0.5)
    front = np.asarray(L.locate_box(box, depth, cam, np.eye(4), T_WC, 0.0, config).point)
    found = np.asarray(BM.box_centre_candidates(front, T_WC, CAR_HALF, box, cam, config)[0][k])
    ray = (front - cam_pos) / np.linalg.norm(front - cam_pos)
    assert np.linalg.norm(found - centre) < 0.25
    assert np.linalg.norm(front + 1.25 * ray - centre) > 2 * np.linalg.norm(found - centre)


def test_border_covariance_opens_the_cut_axis_only():
    R_WC = Rotation.from_euler("zyx", [0.4, 0.1, -0.2]).as_matrix()
    half = np.array([2.1, 0.875, 0.725])
    inside = BM.border_covariance([20, 30, 100, 90], (376, 240), R_WC, half)
    np.testing.assert_allclose(inside, 0.0)
    left = BM.border_covariance([0, 30, 100, 90], (376, 240), R_WC, half)
    np.testing.assert_allclose(left @ R_WC[:, 0], 2.1 ** 2 * R_WC[:, 0])
    np.testing.assert_allclose(left @ R_WC[:, 1], 0.0, atol=1e-12)
    both = BM.border_covariance([0, 30, 100, 240], (376, 240), R_WC, half)
    assert np.linalg.matrix_rank(both) == 2


def test_cut_by_border_against_hand_values():
    from uavcal_jax.track import cut_by_border

    size = (376, 240)
    assert not cut_by_border([10.0, 10.0, 100.0, 100.0], size, 1.0)
    assert cut_by_border([0.5, 10.0, 100.0, 100.0], size, 1.0)  # left edge
    assert cut_by_border([10.0, 10.0, 375.0, 100.0], size, 1.0)  # right edge, within 1 px
    assert cut_by_border([10.0, 10.0, 100.0, 239.5], size, 1.0)  # bottom edge
    assert not cut_by_border([0.0, 0.0, 376.0, 240.0], size, -1.0)  # a negative margin: never


def _iou(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - ix * iy
    return ix * iy / union


def _car_before_floor_and_wall(k: int, wall_x: float | None):
    """A car at heading ``CANDIDATE_HEADINGS[k]`` on the floor, 7 m before a drone 3 m up,
    ray-cast with the floor and, at ``wall_x`` m (``None``: none), a wall behind it: the
    camera, ``T_WC``, the (H, W) z-depth and the car's true box."""
    cam = rig.euroc_camera(0).scaled(0.5)
    centre = np.array([7.0, 0.5, CAR_HALF[2]])
    T_WC = _look_at(np.array([0.0, 0.0, 3.0]), centre)
    car, box = _render_box_depth(cam, T_WC, centre, CAR_HALF, BM.CANDIDATE_HEADINGS[k])
    dirs = _rays(cam) @ T_WC[:3, :3].T  # world directions of the unit-z rays
    with np.errstate(divide="ignore", invalid="ignore"):
        floor = np.where(dirs[..., 2] < 0, -T_WC[2, 3] / dirs[..., 2], np.inf)
        wall = np.inf if wall_x is None else np.where(
            dirs[..., 0] > 0, (wall_x - T_WC[0, 3]) / dirs[..., 0], np.inf)
    return cam, T_WC, np.minimum(car, np.minimum(floor, wall)).astype(np.float32), box


@pytest.mark.parametrize("k", [0, 3, 6, 10])
def test_depth_box_redraws_a_loose_box_around_the_car(k):
    """A car on a floor before a wall, ray-cast from a drone 3 m up and 7 m behind; a loose
    detector box (a tenth of its width to the right, a quarter taller) is redrawn from the
    depth to within IoU 0.9 of the car's true box, the true box stays within 0.9 of itself,
    and a box without depth is left as it is."""
    from uavcal_jax.track.depth_box import DepthBoxConfig, refine_box

    cam, T_WC, depth, box = _car_before_floor_and_wall(k, 14.0)
    w, h = box[2] - box[0], box[3] - box[1]
    loose = box + np.array([0.1 * w, -0.25 * h, 0.1 * w, 0.0])
    config = L.LocateConfig(quantile=0.5)
    front = float(L.box_depth(depth, loose.astype(np.float32), config).depth)
    radius = float(np.hypot(*CAR_HALF[:2]))
    refined = refine_box(loose, depth, front, cam, T_WC, DepthBoxConfig(enabled=True), radius)
    assert _iou(loose, box) < 0.8
    assert _iou(refined, box) > 0.9, (refined, box)
    again = refine_box(box, depth, float(L.box_depth(depth, box.astype(np.float32), config).depth),
                       cam, T_WC, DepthBoxConfig(enabled=True), radius)
    assert _iou(again, box) > 0.9, (again, box)
    np.testing.assert_array_equal(refine_box(loose, np.zeros_like(depth), np.nan, cam, T_WC),
                                  loose)


@pytest.mark.parametrize("axis", ["x", "y"])
def test_depth_box_holds_under_a_pose_whose_gravity_is_two_degrees_off(axis):
    """A VIO's world is tilted by the accelerometer offset it has not yet estimated (the
    demo's 0.22 m/s^2: 1.3-1.6 degrees): the floor behind the car then rises in the believed
    world, and a ground at one height took the floor 6 m further as standing. The ground is
    a plane: the same loose box is still redrawn within IoU 0.9 of the car's true box."""
    from uavcal_jax.track.depth_box import DepthBoxConfig, refine_box

    cam, T_WC, depth, box = _car_before_floor_and_wall(3, 14.0)
    w, h = box[2] - box[0], box[3] - box[1]
    loose = box + np.array([0.1 * w, -0.25 * h, 0.1 * w, 0.0])
    front = float(L.box_depth(depth, loose.astype(np.float32), L.LocateConfig(quantile=0.5)).depth)
    radius = float(np.hypot(*CAR_HALF[:2]))
    for sign in (1.0, -1.0):
        tilt = np.eye(4)
        tilt[:3, :3] = Rotation.from_euler(axis, sign * 2.0, degrees=True).as_matrix()
        refined = refine_box(loose, depth, front, cam, tilt @ T_WC, DepthBoxConfig(), radius)
        assert _iou(refined, box) > 0.9, (sign, refined, box)


def test_the_run_localizer_locates_the_redrawn_box_with_refine_on():
    """``uavcal run``'s Localizer: with ``refine.enabled`` the box it locates (and hands to the
    box model) is the one redrawn from the depth, closer to the car's true box than the loose
    detector box it was given (the default); off, the detector's box as it came."""
    from uavcal_jax.config import apply_overrides
    from uavcal_jax.data.sequence import CameraCalibration
    from uavcal_jax.pipeline.run_config import RunConfig
    from uavcal_jax.pipeline.tracker_locate import FrameSensors, Localizer

    cam, T_WC, depth, box = _car_before_floor_and_wall(5, None)
    calibration = CameraCalibration(np.asarray(cam.intrinsics, float),
                                    np.asarray(cam.distortion, float), cam.resolution, 20.0,
                                    np.eye(4))
    w, h = box[2] - box[0], box[3] - box[1]
    loose = box + np.array([0.12 * w, -0.2 * h, 0.12 * w, 0.05 * h])
    sensors = FrameSensors(depth=lambda: depth)
    located = {}
    for enabled in (False, True):
        config = apply_overrides(RunConfig(), [f"refine.enabled={str(enabled).lower()}"])
        point = Localizer(config, "depth", calibration).locate(loose, T_WC, sensors)
        assert point.located
        located[enabled] = point.box
    np.testing.assert_array_equal(located[False], loose)
    assert _iou(located[True], box) > 0.9 > _iou(loose, box) + 0.15
