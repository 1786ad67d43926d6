"""The simulator's camera model: exposure x gain, shot and read noise, motion blur, the ideal
switch, against the model's own statistics, ray-cast sub-exposures and the real V1_01 frames."""

from __future__ import annotations

import glob

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import shared_path
from scipy.stats import norm

from uavcal_jax.data import euroc_rig as rig
from uavcal_jax.data.euroc_writer import depth_to_millimetres
from uavcal_jax.geometry import camera as C
from uavcal_jax.sim import motion_blur as MB
from uavcal_jax.sim import render as R
from uavcal_jax.sim import sensor as SN
from uavcal_jax.sim.config import SimConfig, sensor_model
from uavcal_jax.sim.frames import (
    CameraEffects,
    camera_effects,
    make_frame_renderer,
    sub_exposure_poses,
)
from uavcal_jax.sim.scene_build import make_scene
from uavcal_jax.sim.simulate import simulate_report
from uavcal_jax.sim.trajectory import Trajectory

# --------------------------------------------------------------------------------------------
# sensor noise and the exposure x gain mapping
# --------------------------------------------------------------------------------------------


def _flat_patches(model: SN.SensorModel, dn_levels, size=200, seed=0):
    """Noisy flat patches at the radiances whose noise-free DN are ``dn_levels``."""
    L = np.asarray(dn_levels, np.float64) / model.mean_dn(1.0)
    patch = jnp.asarray(np.broadcast_to(L[:, None, None], (len(L), size, size)), jnp.float32)
    img = np.asarray(SN.sensor_image(patch, jax.random.PRNGKey(seed), model), np.float64)
    return img.reshape(len(L), -1)


@pytest.mark.parametrize("gain", [1.0, 2.5])
def test_flat_patch_variance_follows_shot_plus_read_noise(gain):
    model = SN.SensorModel(exposure_s=5e-3, gain=gain)
    levels = np.array([20.0, 60.0, 110.0, 170.0, 220.0])
    img = _flat_patches(model, levels)
    mean, var = img.mean(axis=1), img.var(axis=1)
    np.testing.assert_allclose(mean, levels, atol=0.1)  # rounding to the nearest DN: unbiased
    K = model.dn_per_electron
    expected = K * levels + (K * model.read_noise_electrons) ** 2 + 1.0 / 12.0  # + quantisation
    np.testing.assert_allclose(var, expected, rtol=0.08)
    slope = np.polyfit(mean, var, 1)[0]  # the photon-transfer slope is the conversion gain
    np.testing.assert_allclose(slope, K, rtol=0.08)
    # no light, high gain: read noise alone, clipped at 0 DN (never wrapped around to 255)
    high = SN.SensorModel(exposure_s=5e-3, gain=4.0 * gain)
    dark = _flat_patches(high, [0.0], seed=1)[0]
    assert dark.max() < 10
    sigma = high.dn_per_electron * high.read_noise_electrons
    np.testing.assert_allclose(np.mean(dark > 0), norm.sf(0.5 / sigma), rtol=0.2)


def test_exposure_and_gain_scale_brightness_and_noise():
    base = SN.SensorModel(exposure_s=4e-3)
    L = jnp.full((100, 100), 0.08, jnp.float32)
    key = jax.random.PRNGKey(3)
    img = {name: np.asarray(SN.sensor_image(L, key, m), np.float64) for name, m in {
        "base": base, "exposure": SN.SensorModel(exposure_s=8e-3),
        "gain": SN.SensorModel(exposure_s=4e-3, gain=2.0)}.items()}
    m0 = img["base"].mean()
    assert 20 < m0 < 120
    # twice the light or twice the gain: twice the DN
    np.testing.assert_allclose(img["exposure"].mean(), 2 * m0, rtol=0.01)
    np.testing.assert_allclose(img["gain"].mean(), 2 * m0, rtol=0.01)
    # more light: shot noise grows as sqrt(signal) in DN; more gain: as the signal itself
    v0 = img["base"].var()
    assert 1.6 * v0 < img["exposure"].var() < 2.4 * v0
    assert 3.4 * v0 < img["gain"].var() < 4.6 * v0
    # saturation: a bright pixel clips at 255 and does not wrap around
    bright = np.asarray(SN.sensor_image(jnp.full((10, 10), 1.0), key, base))
    assert np.all(bright == 255)
    # the same key gives the same image, another key another
    np.testing.assert_array_equal(np.asarray(SN.sensor_image(L, key, base)), img["base"])
    assert np.any(np.asarray(SN.sensor_image(L, jax.random.PRNGKey(4), base)) != img["base"])


def _real_frames(cam: str) -> np.ndarray:
    root = shared_path("euroc_v101_micro", "mav0", cam, "data")
    files = sorted(glob.glob(str(root / "*.png")))
    return np.stack([cv2.imread(f, cv2.IMREAD_UNCHANGED) for f in files]).astype(np.float64)


@pytest.mark.realdata
def test_default_conversion_gain_matches_real_v101_temporal_noise():
    """The micro slice stands still: consecutive-frame differences are the sensor's temporal
    noise, and their variance against the mean (photon transfer) has the default sensor's
    slope, DN per electron."""
    xs, ys = [], []
    for cam in ("cam0", "cam1"):
        ims = _real_frames(cam)
        mean = ims.mean(axis=0)
        var = (np.diff(ims, axis=0) ** 2).mean(axis=0) / 2.0
        flat = np.hypot(*np.gradient(mean)) < 1.0  # vibration inflates textured pixels
        for lo in range(30, 180, 10):
            sel = (mean >= lo) & (mean < lo + 10) & (ims.max(axis=0) < 255) & flat
            if sel.sum() >= 500:
                xs.append(mean[sel].mean())
                ys.append(np.median(var[sel]))
    (slope, intercept), cov = np.polyfit(xs, ys, 1, cov=True)
    model = sensor_model(SimConfig())
    np.testing.assert_allclose(slope, model.dn_per_electron, rtol=0.1)
    # the dark floor: read noise plus quantisation, within two standard errors of the fit
    floor = (model.dn_per_electron * model.read_noise_electrons) ** 2 + 1.0 / 12.0
    assert abs(floor - intercept) < 2.0 * np.sqrt(cov[1, 1]), (floor, intercept)


@pytest.mark.realdata
def test_simulated_mean_intensity_is_close_to_real_v101(tmp_path):
    """Frames along the whole V1_01 trajectory (one every 5 s) with the default camera are
    about as bright as the real V1_01 frames (band: +-10 % of the real mean; the scenes of the
    11 EuRoC flights spread by 14 DN about it) and spread about as much (+-35 %)."""
    real = _real_frames("cam0")
    traj = shared_path("trajectories", "euroc", "V1_01_easy.txt")
    config = SimConfig(trajectory=str(traj), duration=140.0, camera_rate_hz=0.2,
                       resolution=(188, 120), depth=False, targets=False)
    simulate_report(config, tmp_path / "rec", progress=False)
    files = sorted(glob.glob(str(tmp_path / "rec" / "mav0" / "cam0" / "data" / "*.png")))
    sim = np.stack([cv2.imread(f, cv2.IMREAD_UNCHANGED) for f in files]).astype(np.float64)
    assert len(files) == 29
    print(f"mean intensity: real {real.mean():.1f} (std {real.std():.1f}), simulated "
          f"{sim.mean():.1f} (std {sim.std():.1f})")
    assert abs(sim.mean() - real.mean()) < 0.1 * real.mean()
    assert abs(sim.std() - real.std()) < 0.35 * real.std()


# --------------------------------------------------------------------------------------------
# motion blur
# --------------------------------------------------------------------------------------------

#: An undistorted test lens, 64x48, f = 100 px.
LENS = C.PinholeRadtan.create((100.0, 100.0, 31.5, 23.5), (0.0, 0.0, 0.0, 0.0), (64, 48),
                              jnp.float32)


def _spinning(rate: float, axis=(0.0, 1.0, 0.0)) -> Trajectory:
    """A body at the origin turning at ``rate`` rad/s about ``axis`` (body = world at t=0)."""
    t = np.linspace(0.0, 0.2, 201)
    half = 0.5 * rate * t
    q = np.zeros((len(t), 4))
    q[:, 0] = np.cos(half)
    q[:, 1:] = np.sin(half)[:, None] * np.asarray(axis)
    return Trajectory.from_samples(t, np.zeros((len(t), 3)), q)


def _blur(image, rate, exposure_s, samples=5, depth=2.0):
    traj = _spinning(rate)
    t_ns = np.array([100_000_000])
    rel = sub_exposure_poses(traj, t_ns, np.eye(4), exposure_s, samples, (0, 200_000_000))[0]
    b = R.ray_bundle(LENS)
    out = MB.blur_image(jnp.asarray(image, jnp.float32), jnp.full(image.shape[:2], depth),
                        jnp.asarray(b.rx), jnp.asarray(b.ry), jnp.asarray(rel), LENS)
    return np.asarray(out)


def test_smear_of_a_line_matches_the_projected_rotation():
    """A camera turning about its y axis smears a vertical line over f * rate * exposure pixels:
    with 5 sub-exposures spaced 2 px apart, one fifth of the line lands on each of 5 columns."""
    image = np.zeros((48, 64))
    image[:, 32] = 1.0
    rate, exposure = 10.0 / (100.0 * 0.01), 0.01  # f * rate * exposure = 10 px
    out = _blur(image, rate, exposure)
    row = out[23]
    expected = np.zeros(64)
    expected[[28, 30, 32, 34, 36]] = 0.2
    np.testing.assert_allclose(row, expected, atol=0.01)
    np.testing.assert_allclose(out[10:38].sum(axis=1), 1.0, atol=3e-3)  # light is kept
    # no motion: the warp is the identity
    np.testing.assert_allclose(_blur(image, 0.0, exposure), image, atol=1e-4)


def test_blur_grows_with_rate_and_exposure():
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.uniform(size=(48, 64)), (0, 0), 0.7)

    def energy(img):  # mean squared horizontal gradient inside the image
        return float(np.mean(np.diff(img[8:-8, 8:-8], axis=1) ** 2))

    e = [energy(_blur(image, r, 4e-3)) for r in (0.0, 2.0, 4.0, 8.0)]
    assert e[0] > e[1] > e[2] > e[3], e
    assert e[3] < 0.5 * e[0]
    # the smear depends on rate x exposure
    np.testing.assert_allclose(energy(_blur(image, 2.0, 8e-3)), e[2], rtol=0.02)


def test_warped_blur_matches_mean_of_ray_cast_sub_exposures():
    """The cheap blur (one render warped by its depth) against the mean of ray-cast renders at
    the sub-exposure poses, for a turning and translating camera."""
    path = np.stack([np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 1.5)], axis=1)
    scn = make_scene(path.min(0), path.max(0), seed=2, path_points=path)
    # half resolution: at a quarter the textures alias, and resampling an aliased image is
    # not the ray-cast point sample at the shifted position whatever the warp
    cam = rig.euroc_camera(0).scaled(0.5)
    T_mid = np.eye(4)
    T_mid[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # look +x
    T_mid[:3, 3] = (0.0, 0.0, 1.5)
    S, exposure = 5, 8e-3
    tau = ((np.arange(S) + 0.5) / S - 0.5) * exposure
    rel = []
    for dt in tau:  # 3 rad/s about the camera's y and x, 1.5 m/s sideways
        ang = np.array([1.0, 3.0, 0.0]) * dt
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(ang)[0]
        T[:3, 3] = np.array([1.5, 0.0, 0.0]) * dt
        rel.append(T)
    rel = np.stack(rel)
    subs = R.render_batch(scn, cam, np.einsum("ij,sjk->sik", T_mid, rel), np.zeros(S),
                          color="gray")
    reference = np.asarray(subs.image).mean(axis=0)
    mid = R.render(scn, cam, T_mid, 0.0, color="gray")
    b = R.ray_bundle(cam)
    warped = np.asarray(MB.blur_image(mid.image, mid.depth, jnp.asarray(b.rx), jnp.asarray(b.ry),
                                      jnp.asarray(rel), cam.astype(jnp.float32)))
    inner = (slice(6, -6), slice(6, -6))  # the warp clamps samples beyond the border
    err = np.abs(warped - reference)[inner] * 255
    change = np.abs(np.asarray(mid.image) - reference)[inner] * 255
    assert change.mean() > 1.0  # the blur is visible
    print(f"warp vs ray-cast sub-exposures: mean |error| {err.mean():.2f} DN, median "
          f"{np.median(err):.2f} DN; blur changed the image by {change.mean():.2f} DN")
    assert err.mean() < 0.3 * change.mean() and np.median(err) < 0.2 * np.median(change)


# --------------------------------------------------------------------------------------------
# the frame renderer: ideal switch and determinism
# --------------------------------------------------------------------------------------------


def test_effects_off_is_the_ideal_render_and_noise_is_per_frame():
    path = np.stack([np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 1.5)], axis=1)
    scn = make_scene(path.min(0), path.max(0), seed=1, path_points=path)
    lenses = [rig.euroc_camera(i).scaled(0.125) for i in (0, 1)]
    bundles = [jax.tree_util.tree_map(jnp.asarray, R.ray_bundle(c)) for c in lenses]
    lenses = [c.astype(jnp.float32) for c in lenses]
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = (0.0, 0.0, 1.5)
    T2 = T.copy()
    T2[:3, 3] += (0.1, 0.05, 0.0)
    T_WC = jnp.asarray(np.stack([T, T2]), jnp.float32)
    t = jnp.zeros(2, jnp.float32)
    rel = np.broadcast_to(np.eye(4), (2, 3, 4, 4)).copy()
    rel[:, 0, 0, 3], rel[:, 2, 0, 3] = -0.01, 0.01  # 2 cm sideways over the exposure
    rel = jnp.asarray(rel, jnp.float32)
    key = jax.random.PRNGKey(7)

    def run(effects, frames=(0, 1), sel=slice(None)):
        fn = make_frame_renderer("gray", int(scn.targets.class_id.shape[0]), effects)
        return fn(scn, *bundles, *lenses, T_WC[sel], T_WC[sel], t[sel], rel[sel], rel[sel],
                  jnp.asarray(frames, jnp.int32), key)

    ideal = run(CameraEffects())
    # the pre-camera-model pipeline, verbatim: round(255 L), z-depth in mm
    old = R.render_batch(scn, None, T_WC, t, color="gray", rays=bundles[0])
    np.testing.assert_array_equal(
        np.asarray(ideal[0][0]), np.asarray(jnp.clip(jnp.round(old.image * 255.0), 0, 255)
                                            .astype(jnp.uint8)))
    np.testing.assert_array_equal(np.asarray(ideal[0][1]),
                                  np.asarray(depth_to_millimetres(old.depth, jnp)))
    assert camera_effects(SimConfig(ideal_camera=True)) == CameraEffects()

    full = camera_effects(SimConfig(exposure_ms=5.0, blur_samples=3))
    noisy = run(full)
    again = run(full)
    for c in (0, 1):
        np.testing.assert_array_equal(np.asarray(noisy[c][0]), np.asarray(again[c][0]))
        # depth and labels stay at mid-exposure
        np.testing.assert_array_equal(np.asarray(noisy[c][1]), np.asarray(ideal[c][1]))
        np.testing.assert_array_equal(np.asarray(noisy[c][3]), np.asarray(ideal[c][3]))
    assert np.any(np.asarray(noisy[0][0]) != np.asarray(noisy[1][0]))  # cameras differ
    # a frame's noise depends on its index, not on the batch it is rendered in
    alone = run(full, frames=(1,), sel=slice(1, 2))
    np.testing.assert_array_equal(np.asarray(alone[0][0][0]), np.asarray(noisy[0][0][1]))
    # noise off, no blur: the rounded exposure x gain mapping (float32 products in another
    # order may round a value within an ulp of .5 the other way)
    plain = np.asarray(run(CameraEffects(sensor=full.sensor, noise=False, blur_samples=1))[0][0])
    mapped = np.asarray(full.sensor.mean_dn(np.asarray(old.image, np.float64)))
    reference = np.clip(np.round(mapped), 0, 255)
    near_half = np.abs(mapped - np.floor(mapped) - 0.5) < 1e-3
    np.testing.assert_array_equal(plain[~near_half], reference[~near_half])
    assert np.all(np.abs(plain.astype(float) - reference) <= 1)
