"""VIO front end: KLT tracking on real EuRoC frames and on images warped by known motions,
bad frames, and the gyro-compensated keyframe decision."""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.euroc_rig import EUROC_CAM0_T_BS, EUROC_CAM1_T_BS, euroc_camera
from uavcal_jax.data.sequence import CameraCalibration
from uavcal_jax.geometry.camera import pixels_to_normalized
from uavcal_jax.vio.config import NOMINAL_FOCAL_PX, FrontendConfig, KeyframeConfig
from uavcal_jax.vio.frontend import FeatureTracker, FrameFeatures
from uavcal_jax.vio.keyframes import (
    body_to_camera_rotation,
    compensated_parallax,
    keyframe_decision,
)
from uavcal_jax.vio.match_checks import reject_outliers

W, H = 752, 480
N_REAL = 20


def _rotation(axis, angle_rad) -> np.ndarray:
    rvec = np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle_rad
    return cv2.Rodrigues(rvec)[0]


def _pinhole(T_BS=None) -> CameraCalibration:
    """A distortion-free 752x480 camera, so image warps are exact camera motions."""
    return CameraCalibration(intrinsics=np.array([458.0, 457.0, 376.0, 240.0]),
                             distortion=np.zeros(4), resolution=(W, H), rate_hz=20.0,
                             T_BS=np.eye(4) if T_BS is None else T_BS)


def _texture(seed=0, sigma=2.0) -> np.ndarray:
    """(H, W) float32 smooth random texture in [20, 235] (corners everywhere)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.normal(size=(H, W)).astype(np.float32), (0, 0), sigma)
    img = (img - img.min()) / (img.max() - img.min())
    return (20 + 215 * img).astype(np.float32)


def _u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _pairwise_min(uv: np.ndarray) -> float:
    d = np.linalg.norm(uv[:, None] - uv[None], axis=-1)
    return float(d[~np.eye(len(uv), dtype=bool)].min())


def _check_layout(f: FrameFeatures, cap: int) -> None:
    for a in (f.ids, f.mask, f.stereo_mask, f.age):
        assert a.shape == (cap,)
    for a in (f.uv, f.xy, f.uv_right, f.xy_right):
        assert a.shape == (cap, 2) and a.dtype == np.float64
    n = f.n_tracked
    assert f.mask[:n].all() and not f.mask[n:].any(), "valid rows come first"
    assert (f.ids[n:] == -1).all() and (f.ids[:n] >= 0).all()
    assert len(np.unique(f.ids[:n])) == n
    assert not (f.stereo_mask & ~f.mask).any()
    assert (f.age[:n] >= 1).all()
    assert np.isfinite(f.uv).all() and np.isfinite(f.xy).all() and np.isfinite(f.xy_right).all()


# --- real EuRoC frames ---------------------------------------------------------------------


@functools.lru_cache(maxsize=1)
def _load_frames(root: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = read_euroc(root)
    c0, c1 = seq.camera("cam0"), seq.camera("cam1")
    return seq, [(c0.t[i], c0.load(i), c1.load(i)) for i in range(N_REAL)]


@pytest.fixture
def euroc_frames(euroc_micro):
    """The real sequence and its first stereo frames ``(t, left, right)``, read once."""
    return _load_frames(str(euroc_micro))


def _run(seq, frames, config=None):
    tracker = FeatureTracker.from_sequence(seq, config)
    return tracker, [tracker.track(t, a, b) for t, a, b in frames]


def test_real_tracks_ids_ages_and_forward_backward(euroc_frames):
    seq, frames = euroc_frames
    cfg = FrontendConfig()
    tracker, out = _run(seq, frames, cfg)
    lk = dict(winSize=(cfg.lk_window_px,) * 2, maxLevel=cfg.lk_max_level)
    for k, f in enumerate(out):
        _check_layout(f, cfg.max_features)
        assert f.n_tracked >= 100, f"frame {k}: {f.n_tracked} features"
        assert f.n_stereo >= 50, f"frame {k}: {f.n_stereo} stereo matches"
        if k == 0:
            assert f.n_new == f.n_tracked and (f.age[f.mask] == 1).all()
            continue
        prev = out[k - 1]
        common, i_prev, i_cur = np.intersect1d(prev.ids[prev.mask], f.ids[f.mask],
                                               return_indices=True)
        assert len(common) >= 100
        # A surviving id is one track: its age grows by one per frame.
        np.testing.assert_array_equal(f.age[i_cur], prev.age[i_prev] + 1)
        assert (f.age[f.mask & ~np.isin(f.ids, common)] == 1).all()
        # Independent re-check: tracked back into the previous image, every surviving
        # feature lands within the forward-backward threshold of its previous position.
        img0, img1 = cv2.equalizeHist(frames[k - 1][1]), cv2.equalizeHist(frames[k][1])
        back, st, _ = cv2.calcOpticalFlowPyrLK(img1, img0, f.uv[i_cur].astype(np.float32),
                                               None, **lk)
        err = np.linalg.norm(back - prev.uv[i_prev], axis=1)
        assert st.all() and err.max() <= cfg.fb_threshold_px + 1e-3
    # The sequence barely moves in its first second: most tracks live through all frames.
    assert np.sum(out[-1].age == N_REAL) >= 100
    assert tracker.last_timings["total"] > 0


def test_real_normalised_coordinates_match_camera_model(euroc_frames, x64):
    seq, frames = euroc_frames
    _, out = _run(seq, frames[:2])
    f = out[-1]
    for uv, xy, cam in ((f.uv[f.mask], f.xy[f.mask], euroc_camera(0)),
                        (f.uv_right[f.stereo_mask], f.xy_right[f.stereo_mask], euroc_camera(1))):
        ref = np.asarray(pixels_to_normalized(jnp.asarray(uv), cam))
        np.testing.assert_allclose(xy, ref, atol=1e-10)


def test_real_stereo_matches_satisfy_epipolar_constraint(euroc_frames):
    seq, frames = euroc_frames
    cam0, cam1 = euroc_camera(0), euroc_camera(1)
    T = np.linalg.inv(EUROC_CAM0_T_BS) @ EUROC_CAM1_T_BS  # cam1 in cam0
    R, t = T[:3, :3], T[:3, 3]
    E = np.cross(np.eye(3), t) @ R  # [t]x R with x0^T E x1 = 0
    K0, K1 = np.asarray(cam0.K, np.float64), np.asarray(cam1.K, np.float64)
    F = np.linalg.inv(K0).T @ E @ np.linalg.inv(K1)

    def sampson_px(frames):
        # One call per camera over all frames: the camera model compiles once per shape.
        x0 = np.asarray(pixels_to_normalized(
            jnp.asarray(np.concatenate([f.uv[f.stereo_mask] for f in frames])), cam0))
        x1 = np.asarray(pixels_to_normalized(
            jnp.asarray(np.concatenate([f.uv_right[f.stereo_mask] for f in frames])), cam1))
        p0 = np.c_[x0, np.ones(len(x0))] @ K0.T  # undistorted pixels
        p1 = np.c_[x1, np.ones(len(x1))] @ K1.T
        Fp1, Ftp0 = p1 @ F.T, p0 @ F
        r = np.sum(p0 * Fp1, axis=1)
        return np.abs(r) / np.sqrt(Fp1[:, 0] ** 2 + Fp1[:, 1] ** 2 + Ftp0[:, 0] ** 2
                                   + Ftp0[:, 1] ** 2)

    # Without the tracker's own epipolar gate: LK + forward-backward alone give matches that
    # agree with the calibrated extrinsic to a fraction of a pixel.
    _, out = _run(seq, frames[::4], FrontendConfig(stereo_epipolar_px=math.inf))
    d = sampson_px(out)
    assert len(d) >= 50 * len(out)
    assert d.mean() < 1.0 and np.median(d) < 0.3
    # With it, every match is within the gate (the tracker's distance is symmetric point-to-
    # line; Sampson's first-order distance is within a factor ~sqrt(2) of it).
    cfg = FrontendConfig()
    _, out = _run(seq, frames[:3], cfg)
    d = sampson_px(out)
    assert d.max() <= cfg.stereo_epipolar_px * 1.5 and d.mean() < 0.5


def test_real_stereo_seeded_by_previous_disparity_finds_the_same_matches(euroc_frames):
    # Seeding the left-right flow with the previous frame's disparity (one pyramid level)
    # must land where the full pyramid search lands, and lose no matches to speak of.
    seq, frames = euroc_frames
    _, seeded = _run(seq, frames, FrontendConfig())
    _, full = _run(seq, frames, FrontendConfig(stereo_seed_disparity=False))
    for k, (a, b) in enumerate(zip(seeded, full, strict=True)):
        np.testing.assert_array_equal(a.ids, b.ids)  # the temporal tracks are untouched
        both = a.stereo_mask & b.stereo_mask
        assert a.n_stereo >= b.n_stereo - 3, f"frame {k}: {a.n_stereo} vs {b.n_stereo}"
        assert both.sum() >= b.n_stereo - 3
        np.testing.assert_allclose(a.uv_right[both], b.uv_right[both], atol=0.05)


def test_real_corners_respect_min_distance(euroc_frames):
    seq, frames = euroc_frames
    cfg = FrontendConfig()
    _, out = _run(seq, frames[:8], cfg)
    for f in out:
        # Circles are rasterised at rounded centres: allow a pixel and a half.
        assert _pairwise_min(f.uv[f.mask]) >= cfg.min_distance_px - 1.5


# --- images warped by known motions ---------------------------------------------------------


@pytest.mark.parametrize("shift", [(3.3, -1.7), (-11.6, 7.2)])
def test_translation_is_recovered_to_a_tenth_of_a_pixel(shift):
    tex = _texture(1)
    M = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
    moved = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    tracker = FeatureTracker(_pinhole(), config=FrontendConfig(equalize="none"))
    f0 = tracker.track(0.0, _u8(tex))
    f1 = tracker.track(0.05, _u8(moved))
    assert f0.n_tracked == 150 and f1.n_stereo == 0
    _, i0, i1 = np.intersect1d(f0.ids[f0.mask], f1.ids[f1.mask], return_indices=True)
    inside = np.all((f0.uv[i0] > 25) & (f0.uv[i0] < [W - 25, H - 25]), axis=1)
    assert inside.sum() >= 100
    err = np.linalg.norm(f1.uv[i1] - f0.uv[i0] - shift, axis=1)[inside]
    assert np.median(err) < 0.03 and err.max() < 0.1


def test_gyro_prediction_tracks_a_fast_rotation():
    # An 8 deg yaw between frames (~65 px of flow) on a fine texture that the coarse pyramid
    # levels blur away: unseeded LK loses nearly every track; the gyro rotation, given in a
    # body frame that is not the camera's, seeds it. (The residual error is LK's translation-
    # only window under the rotation's perspective deformation: 0.02 px at 1 deg.)
    R_BC = _rotation([0.3, -1.0, 0.5], 1.1)
    T_BS = np.eye(4)
    T_BS[:3, :3] = R_BC
    cal = _pinhole(T_BS)
    K = cal.K
    R_c0_c1 = _rotation([0.1, 1.0, 0.05], np.radians(8.0))
    Hm = K @ R_c0_c1.T @ np.linalg.inv(K)  # previous pixels -> current pixels
    tex = _texture(2, sigma=3.0)
    moved = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR)
    R_b0_b1 = R_BC @ R_c0_c1 @ R_BC.T
    np.testing.assert_allclose(body_to_camera_rotation(R_b0_b1, R_BC), R_c0_c1, atol=1e-12)

    def run(R):
        tracker = FeatureTracker(cal, config=FrontendConfig(equalize="none"))
        f0 = tracker.track(0.0, _u8(tex))
        f1 = tracker.track(0.05, _u8(moved), R_prev_curr_gyro=R)
        _, i0, i1 = np.intersect1d(f0.ids[f0.mask], f1.ids[f1.mask], return_indices=True)
        p = np.c_[f0.uv[i0], np.ones(len(i0))] @ Hm.T
        return np.linalg.norm(f1.uv[i1] - p[:, :2] / p[:, 2:], axis=1)

    seeded = run(R_b0_b1)
    assert len(seeded) >= 90 and np.median(seeded) < 0.2 and np.percentile(seeded, 90) < 0.5
    assert len(run(None)) < 10


@pytest.mark.parametrize("method", ["fundamental", "essential"])
def test_ransac_rejects_matches_off_the_epipolar_geometry(method):
    # A 3D scene seen before and after a camera motion, 0.2 px noise; 15 % of the matches are
    # displaced 4-20 px across their epipolar line.
    rng = np.random.default_rng(5)
    n = 150
    X0 = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(2.0, 8.0, n)]
    R, t = _rotation([0.3, 1.0, 0.2], np.radians(4.0)), np.array([0.15, -0.05, 0.1])
    X1 = (X0 - t) @ R  # X1 = R^T (X0 - t)
    f = NOMINAL_FOCAL_PX
    xy0 = _normalised(X0) + rng.normal(0, 0.2 / f, (n, 2))
    xy1 = _normalised(X1) + rng.normal(0, 0.2 / f, (n, 2))
    E = np.cross(np.eye(3), t) @ R  # x0^T E x1 = 0
    bad = rng.random(n) < 0.15
    lines = np.c_[xy0, np.ones(n)] @ E  # epipolar lines of x1
    normal = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    xy1[bad] += normal[bad] * rng.uniform(4, 20, (bad.sum(), 1)) / f * rng.choice([-1, 1], (
        bad.sum(), 1))
    inliers = reject_outliers(xy0, xy1, FrontendConfig(outlier_method=method))
    assert inliers.shape == (n,) and bad.sum() >= 15
    assert not (inliers & bad).any(), "every displaced match is rejected"
    assert inliers[~bad].mean() > 0.98
    classic = reject_outliers(xy0, xy1, FrontendConfig(outlier_method=method,
                                                       estimator="ransac"))
    assert not (classic & bad).any() and classic[~bad].mean() > 0.8
    assert reject_outliers(xy0, xy1, FrontendConfig(outlier_method="none")).all()
    assert reject_outliers(xy0[:7], xy1[:7], FrontendConfig()).all(), "too few to fit"


@pytest.mark.parametrize("method", ["fundamental", "essential"])
def test_ransac_on_degenerate_matches_keeps_them_instead_of_raising(method, monkeypatch):
    # Half the points on one spot, or all on a line, barely moving: OpenCV 5's USAC asserts
    # "!model.empty()" on some such sets (found by a search like this one, and on a simulated
    # MH_01 flight) where 4.x returned no model. Whatever the OpenCV version, no set raises.
    rng = np.random.default_rng(0)
    config = FrontendConfig(outlier_method=method)
    for trial in range(600):
        n = int(rng.integers(8, 40))
        xy0 = rng.normal(size=(n, 2))
        if trial % 3:
            xy0[: n // 2] = xy0[0]
        else:
            xy0[:, 1] = 0.3 * xy0[:, 0]
        xy1 = xy0 + rng.normal(scale=3e-3, size=xy0.shape)
        inliers = reject_outliers(xy0, xy1, config)
        assert inliers.shape == (n,) and inliers.dtype == bool

    # where OpenCV raises, nothing is rejected: the same as a set that gives no model
    def failing(*args, **kwargs):
        raise cv2.error("(-215:Assertion failed) !model.empty() in function 'setModelParameters'")

    monkeypatch.setattr(cv2, "findFundamentalMat", failing)
    monkeypatch.setattr(cv2, "findEssentialMat", failing)
    xy = rng.normal(size=(20, 2))
    assert reject_outliers(xy, xy + 1e-3, config).all()
    # nor where it finds fewer inliers than a minimal sample (USAC's all-zero mask)
    monkeypatch.setattr(cv2, "findFundamentalMat", lambda *a, **k: (None, np.zeros((20, 1))))
    monkeypatch.setattr(cv2, "findEssentialMat", lambda *a, **k: (None, np.zeros((20, 1))))
    assert reject_outliers(xy, xy + 1e-3, config).all()


# --- bad frames -----------------------------------------------------------------------------


def test_black_and_blank_frames_give_no_features_and_tracking_recovers():
    tex = _u8(_texture(4))
    rng = np.random.default_rng(0)
    blank = np.clip(128 + rng.normal(0, 0.5, (H, W)), 0, 255).astype(np.uint8)
    bad = [np.zeros((H, W), np.uint8), np.full((H, W), 255, np.uint8), blank]
    # A right camera 0.11 m to the right seeing a fronto-parallel plane 5 m away: its image
    # is the left one shifted left by the disparity f b / Z.
    T_BS1 = np.eye(4)
    T_BS1[0, 3] = 0.11
    right = _u8(cv2.warpAffine(_texture(4), np.array([[1.0, 0, -458.0 * 0.11 / 5.0],
                                                      [0, 1.0, 0]]), (W, H),
                               borderMode=cv2.BORDER_REFLECT))
    cfg = FrontendConfig()
    tracker = FeatureTracker(_pinhole(), _pinhole(T_BS1), cfg)
    first = tracker.track(0.0, np.zeros((H, W), np.uint8), np.zeros((H, W), np.uint8))
    assert first.n_tracked == 0 and first.ids.shape == (cfg.max_features,)
    f = tracker.track(0.05, tex, right)
    assert f.n_tracked >= 100 and f.n_stereo >= 100
    np.testing.assert_allclose(np.median(f.uv[f.stereo_mask] - f.uv_right[f.stereo_mask], 0),
                               [458.0 * 0.11 / 5.0, 0.0], atol=0.05)
    seen = set(f.ids[f.mask].tolist())
    for k, img in enumerate(bad):
        for img_right in (img, None):
            out = tracker.track(0.1 + k, img, img_right)
            _check_layout(out, cfg.max_features)
            assert out.n_tracked == 0 and out.n_stereo == 0
        f = tracker.track(0.2 + k, tex, right)
        assert f.n_tracked >= 100 and f.n_stereo >= 100 and (f.age[f.mask] == 1).all()
        assert not seen & set(f.ids[f.mask].tolist()), "ids are never reused"
        seen |= set(f.ids[f.mask].tolist())
        f = tracker.track(0.3 + k, tex, right)
        assert f.n_tracked >= 100 and (f.age[f.mask] == 2).sum() >= 100


def test_config_rejects_bad_values():
    for bad in (dict(outlier_method="homography"), dict(equalize="gamma"), dict(estimator="x"),
                dict(lk_window_px=20), dict(redetect_below=200), dict(fb_threshold_px=0.0)):
        with pytest.raises(ValueError):
            FrontendConfig(**bad)
    with pytest.raises(ValueError):
        KeyframeConfig(min_parallax_px=-1.0)
    assert dataclasses.replace(FrontendConfig(), max_features=200).max_features == 200
    with pytest.raises(ValueError, match="radial-tangential"):
        FeatureTracker(dataclasses.replace(_pinhole(), distortion_model="equidistant"))


# --- keyframes ------------------------------------------------------------------------------


def _scene(n=120, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(2.0, 6.0, n)]
    return pts, np.arange(n)


def _normalised(points):
    return points[:, :2] / points[:, 2:]


def test_pure_rotation_is_compensated_and_not_a_keyframe():
    pts_kf, ids = _scene()
    R_kf_cur = _rotation([0.2, 1.0, -0.1], np.radians(6.0))
    pts_cur = pts_kf @ R_kf_cur  # X_cur = R_kf_cur^T X_kf, as rows
    xy_kf, xy_cur = _normalised(pts_kf), _normalised(pts_cur)
    mask = np.ones(len(ids), bool)
    par, valid = compensated_parallax(xy_kf, xy_cur, R_kf_cur)
    assert valid.all() and par.max() < 1e-12
    # parallax alone (the turn rule, max_rotation_deg, has its own test)
    parallax_only = KeyframeConfig(max_rotation_deg=90.0)
    comp = keyframe_decision(ids, xy_kf, ids, xy_cur, mask, R_kf_cur, parallax_only)
    raw = keyframe_decision(ids, xy_kf, ids, xy_cur, mask, None, parallax_only)
    assert not comp.is_keyframe and comp.reason == "" and comp.parallax_px < 1e-9
    assert comp.parallax_uncompensated_px > 3 * KeyframeConfig().min_parallax_px
    assert raw.is_keyframe and raw.reason == "parallax"
    assert comp.n_common == comp.n_tracked == len(ids)


def test_a_turn_past_max_rotation_is_a_keyframe_without_parallax():
    """A turn on the spot: no compensated parallax, but past ``max_rotation_deg`` (5) the
    frame is a keyframe, so the window keeps up with a view that sweeps past."""
    pts_kf, ids = _scene(seed=4)
    mask = np.ones(len(ids), bool)
    for degrees, expect in ((4.0, ""), (7.0, "rotation")):
        R_kf_cur = _rotation([0.1, 1.0, 0.2], np.radians(degrees))
        d = keyframe_decision(ids, _normalised(pts_kf), ids, _normalised(pts_kf @ R_kf_cur),
                              mask, R_kf_cur)
        assert d.reason == expect and d.is_keyframe is bool(expect) and d.parallax_px < 1e-9
    # the turn rule waits rotation_min_interval_s (0.25 s) after the last keyframe
    early = keyframe_decision(ids, _normalised(pts_kf), ids, _normalised(pts_kf @ R_kf_cur),
                              mask, R_kf_cur, elapsed_s=0.1)
    assert not early.is_keyframe
    loose = KeyframeConfig(max_rotation_deg=10.0)
    assert not keyframe_decision(ids, _normalised(pts_kf), ids, _normalised(pts_kf @ R_kf_cur),
                                 mask, R_kf_cur, loose).is_keyframe


def test_rotation_from_the_gyro_in_the_body_frame():
    pts_kf_cam, ids = _scene(seed=1)
    R_BC = _rotation([1.0, 0.2, 0.4], 1.9)
    R_b_kf_cur = _rotation([0.0, 0.3, 1.0], np.radians(8.0))
    # Camera points through the body: X_b = R_BC X_c; the body rotates by R_b_kf_cur.
    pts_cur_cam = (pts_kf_cam @ R_BC.T @ R_b_kf_cur) @ R_BC
    R_c = body_to_camera_rotation(R_b_kf_cur, R_BC)
    d = keyframe_decision(ids, _normalised(pts_kf_cam), ids, _normalised(pts_cur_cam),
                          np.ones(len(ids), bool), R_c, KeyframeConfig(max_rotation_deg=90.0))
    assert not d.is_keyframe and d.parallax_px < 1e-9


def test_translation_makes_a_keyframe_and_small_motion_does_not():
    pts_kf, ids = _scene(seed=2)
    R = _rotation([1.0, 0.0, 0.0], np.radians(3.0))
    xy_kf = _normalised(pts_kf)
    mask = np.ones(len(ids), bool)
    for baseline, expect in ((0.25, True), (0.01, False)):
        pts_cur = (pts_kf - [baseline, 0.0, 0.0]) @ R  # moved right by the baseline, rotated
        d = keyframe_decision(ids, xy_kf, ids, _normalised(pts_cur), mask, R)
        assert d.is_keyframe is expect, d
        # Mean parallax of a sideways move: baseline / depth, times the nominal focal.
        approx = np.mean(baseline / pts_kf[:, 2]) * NOMINAL_FOCAL_PX
        assert d.parallax_px == pytest.approx(approx, rel=0.35)


def test_keyframe_track_count_rules():
    pts, ids = _scene(seed=3)
    xy = _normalised(pts)
    all_ = np.ones(len(ids), bool)
    assert keyframe_decision(None, None, ids, xy, all_).reason == "first"
    few = np.zeros(len(ids), bool)
    few[:10] = True
    assert keyframe_decision(ids, xy, ids, xy, few).reason == "few_tracked"
    # 30 of the keyframe's features remain, 90 are new: too little shared with the keyframe.
    cur_ids = np.where(np.arange(len(ids)) < 30, ids, ids + 1000)
    d = keyframe_decision(ids, xy, cur_ids, xy, all_)
    assert d.reason == "few_common" and d.n_common == 30
    # Padding rows (id -1) never count.
    padded = np.r_[ids, -np.ones(30, int)]
    d = keyframe_decision(padded, np.r_[xy, np.zeros((30, 2))], ids, xy, all_)
    assert not d.is_keyframe and d.n_common == len(ids) and d.parallax_px == 0.0


def test_excluded_boxes_hold_no_track_and_no_new_corner():
    """A moving object's box (``exclude``, grown by ``exclude_margin``): the tracks that land
    in it end, and no corner is detected there; the rest of the image keeps its tracks."""
    tex = _texture(2)
    M = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -1.0]])
    moved = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    cfg = FrontendConfig(equalize="none", exclude_margin=0.1)
    box = np.array([[60.0, 40.0, 260.0, 200.0]])
    grown = np.array([40.0, 24.0, 280.0, 216.0])  # 10 % of 200 x 160 more on each side

    def inside(f):
        uv = f.uv[f.mask]
        return np.all((uv >= grown[:2]) & (uv < grown[2:]), axis=1)

    plain = FeatureTracker(_pinhole(), config=cfg)
    f0 = plain.track(0.0, _u8(tex))
    assert inside(f0).sum() > 10  # the texture has corners there
    masked = FeatureTracker(_pinhole(), config=cfg)
    g0 = masked.track(0.0, _u8(tex), exclude=box)
    assert not inside(g0).any() and g0.n_tracked > 100
    # tracked from an unmasked frame into a masked one: those in the box end there
    g1 = plain.track(0.05, _u8(moved), exclude=box)
    assert not inside(g1).any()
    kept = np.intersect1d(f0.ids[f0.mask][~inside(f0)], g1.ids[g1.mask])
    assert len(kept) > 0.8 * (~inside(f0)).sum() - 10
    # an empty box list changes nothing
    again = FeatureTracker(_pinhole(), config=cfg).track(0.0, _u8(tex), exclude=np.zeros((0, 4)))
    np.testing.assert_array_equal(again.uv, f0.uv)


def _two_motions(rng, n_static: int, n_moving: int):
    """Normalised matches of a static scene seen from a camera moving forward-right, and of a
    near object moving across it (its own motion added), previous -> current frame; and the
    camera's true motion (4, 4: the current camera in the previous one's frame)."""
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
    t = np.array([0.15, 0.0, 0.2])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t

    def view(X0, motion):  # points in the previous camera frame -> both frames' pixels
        X1 = (X0 - t - motion) @ R  # R^T (X0 - t - motion), row-wise
        return X0[:, :2] / X0[:, 2:], X1[:, :2] / X1[:, 2:]

    scene = np.column_stack([rng.uniform(-4, 4, (n_static, 2)), rng.uniform(6, 15, n_static)])
    car = np.column_stack([rng.uniform(-1, 1, (n_moving, 2)), rng.uniform(3, 4, n_moving)])
    s0, s1 = view(scene, np.zeros(3))
    c0, c1 = view(car, np.array([0.0, -0.3, 0.0]))
    noise = rng.normal(0, 0.3 / NOMINAL_FOCAL_PX, (n_static + n_moving, 2))
    return np.vstack([s0, c0]), np.vstack([s1, c1]) + noise, T


def test_a_consensus_the_imu_does_not_explain_gives_way_to_the_rest():
    """A moving object with more tracks than the static scene wins RANSAC; under the predicted
    motion its tracks are off their epipolar lines and the scene's are on them, so the
    scene's consensus replaces it. A static scene's consensus, or no translation predicted:
    RANSAC's answer stands."""
    from uavcal_jax.vio.match_checks import imu_consistent_inliers

    rng = np.random.default_rng(3)
    cfg = FrontendConfig()
    xy0, xy1, T = _two_motions(rng, 40, 90)
    static = np.arange(130) < 40
    ransac = reject_outliers(xy0, xy1, cfg)
    # the car won (with the scene's points that happen to fit its motion too)
    assert ransac[~static].mean() > 0.9 and ransac[static].mean() < 0.5
    checked = imu_consistent_inliers(xy0, xy1, ransac, T, cfg)
    assert not checked[~static].any() and checked[static].sum() >= 20
    # no translation predicted: nothing is decided; switched off: neither
    T_rot = T.copy()
    T_rot[:3, 3] = 0.0
    np.testing.assert_array_equal(imu_consistent_inliers(xy0, xy1, ransac, T_rot, cfg), ransac)
    off = dataclasses.replace(cfg, imu_consensus=False)
    np.testing.assert_array_equal(imu_consistent_inliers(xy0, xy1, ransac, T, off), ransac)
    # a static scene with mistracks: RANSAC's consensus is the scene, the prediction agrees
    xy0, xy1, T = _two_motions(rng, 100, 0)
    xy1[:12] += rng.uniform(-0.05, 0.05, (12, 2))  # 12 tracks up to 23 px off
    ransac = reject_outliers(xy0, xy1, cfg)
    assert ransac[12:].mean() > 0.9
    np.testing.assert_array_equal(imu_consistent_inliers(xy0, xy1, ransac, T, cfg), ransac)
