"""The simulator's camera model: exposure x gain, shot and read noise, motion blur, the ideal
switch, vignetting, auto-exposure and rolling shutter, against the model's own statistics,
formulas, ray-cast sub-exposures and the real V1_01 frames; the noise-curve measurement
(``sim.sensor_fit``) against synthetic frames of known noise."""

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
from uavcal_jax.sim import auto_exposure as AE
from uavcal_jax.sim import motion_blur as MB
from uavcal_jax.sim import render as R
from uavcal_jax.sim import sensor as SN
from uavcal_jax.sim import sensor_fit as SF
from uavcal_jax.sim.config import EUROC_CAMERA_PRESET, IDEAL_SENSORS, SimConfig, sensor_model
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


def test_noise_curve_recovers_a_known_shot_and_read_noise():
    """Synthetic static frames (flat patches, Poisson shot noise, Gaussian read noise, 8-bit
    rounding; drawn here, not by the simulator) give back their conversion gain and read
    noise."""
    rng = np.random.default_rng(0)
    K, read_e = 0.02, 40.0  # DN per electron; electrons rms (0.8 DN)
    levels = np.repeat(np.arange(25.0, 240.0, 20.0), 40)  # 11 patches of 40 columns
    lam = np.broadcast_to(levels / K, (60, 50, levels.size))  # 60 frames, 50 rows
    frames = np.clip(np.round(K * (rng.poisson(lam) + rng.normal(0.0, read_e, lam.shape))),
                     0, 255)
    for estimator in SF.ESTIMATORS:
        curve = SF.noise_curve(frames, estimator=estimator, min_pixels=100)
        assert curve.mean_dn.size == 11
        fit = SF.fit_shot_read(curve)
        np.testing.assert_allclose(fit.dn_per_electron, K, rtol=0.05)
        np.testing.assert_allclose(fit.read_noise_electrons, read_e, rtol=0.15)
        np.testing.assert_allclose(curve.std_dn, np.sqrt(K * levels[::40] + (K * read_e) ** 2
                                                         + 1 / 12), rtol=0.05)
    # a slow brightness drift (2 % over the frames) inflates the "std" estimator only
    drift = frames * np.linspace(0.99, 1.01, 60)[:, None, None]
    std = SF.noise_curve(drift, estimator="std", min_pixels=100).variance_dn2
    diff = SF.noise_curve(drift, estimator="difference", min_pixels=100).variance_dn2
    assert std[-1] > 1.2 * diff[-1]
    np.testing.assert_allclose(diff, SF.noise_curve(frames, min_pixels=100).variance_dn2,
                               rtol=0.03)


@pytest.mark.realdata
def test_default_conversion_gain_matches_real_v101_temporal_noise():
    """The micro slice stands still: consecutive-frame differences are the sensor's temporal
    noise, and their variance against the mean (photon transfer) has the default sensor's
    slope, DN per electron; the simulator's sensor, given the real mean image as its signal,
    has the real noise curve within 10 %."""
    curves, sim_std = [], []
    model = sensor_model(SimConfig())
    for cam in ("cam0", "cam1"):
        ims = _real_frames(cam)
        curves.append(SF.noise_curve(ims, lo=30, hi=180))
        L = jnp.asarray(ims.mean(axis=0) / model.mean_dn(1.0), jnp.float32)
        sim = np.stack([np.asarray(SN.sensor_image(L, jax.random.PRNGKey(i), model))
                        for i in range(ims.shape[0])])
        sim_curve = SF.noise_curve(sim, lo=30, hi=180)
        sim_std.append(np.interp(curves[-1].mean_dn, sim_curve.mean_dn, sim_curve.std_dn))
        print(f"{cam} noise curve (mean DN: real std / simulated std):",
              " ".join(f"{m:.0f}: {r:.3f}/{s:.3f}" for m, r, s in zip(
                  curves[-1].mean_dn, curves[-1].std_dn, sim_std[-1], strict=True)))
    pooled = SF.NoiseCurve(*(np.concatenate([getattr(c, f) for c in curves])
                             for f in ("mean_dn", "variance_dn2", "pixels")))
    fit = SF.fit_shot_read(pooled)
    np.testing.assert_allclose(fit.dn_per_electron, model.dn_per_electron, rtol=0.1)
    # the dark floor: read noise plus quantisation, within two standard errors of the fit
    floor = (model.dn_per_electron * model.read_noise_electrons) ** 2 + 1.0 / 12.0
    assert abs(floor - fit.intercept_dn2) < 2.0 * fit.intercept_se, (floor, fit.intercept_dn2)
    real_std = np.concatenate([c.std_dn for c in curves])
    np.testing.assert_allclose(np.concatenate(sim_std), real_std, rtol=0.1)


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

    # the basic camera model (fixed exposure and gain; AE and vignetting have their own tests)
    full = camera_effects(SimConfig(exposure_ms=5.0, blur_samples=3, **IDEAL_SENSORS))
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


# --------------------------------------------------------------------------------------------
# vignetting, auto-exposure, rolling shutter
# --------------------------------------------------------------------------------------------


def _frame_renderer_inputs(lens, frames=1):
    """A scene, and (bundles, lenses, T_WC, t, rel) for :func:`make_frame_renderer` with
    ``lens`` as both cameras, looking along +x from 1.5 m up, ``frames`` times."""
    path = np.stack([np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 1.5)], axis=1)
    scn = make_scene(path.min(0), path.max(0), seed=1, path_points=path)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = (0.0, 0.0, 1.5)
    bundle = jax.tree_util.tree_map(jnp.asarray, R.ray_bundle(lens))
    T_WC = jnp.asarray(np.broadcast_to(T, (frames, 4, 4)), jnp.float32)
    rel = jnp.asarray(np.broadcast_to(np.eye(4), (frames, 1, 4, 4)), jnp.float32)
    return scn, (bundle, bundle, lens, lens, T_WC, T_WC, jnp.zeros(frames), rel, rel)


def test_vignetting_and_exposure_settings_scale_the_frame_as_their_formulas():
    """Noise off: the vignetted frame is the plain one times cos(theta)^p (theta the pixel
    ray's angle to the optical axis, here atan(r / f) with an undistorted lens), down to
    cos^4(21.5 deg) = 0.75 at the corners; per-frame auto-exposure settings scale it by
    exposure x gain."""
    scn, args = _frame_renderer_inputs(LENS, frames=2)
    n = int(scn.targets.class_id.shape[0])
    sensor = SN.SensorModel(exposure_s=2e-3)
    key, frame = jax.random.PRNGKey(0), jnp.arange(2, dtype=jnp.int32)
    # frame 0 at the sensor's own settings, frame 1 at twice the exposure and 1.5x the gain
    settings = jnp.asarray([[2e-3, 1.0], [4e-3, 1.5]], jnp.float32)
    ae = make_frame_renderer("gray", n, CameraEffects(sensor=sensor, auto_exposure=True))(
        scn, *args, frame, key, settings)[0][0]
    plain = np.asarray(ae[0], np.float64)
    vig = np.asarray(make_frame_renderer("gray", n, CameraEffects(sensor=sensor, vignetting=4.0))(
        scn, *args, frame, key)[0][0][0], np.float64)
    v, u = np.mgrid[0:48, 0:64]
    theta = np.arctan(np.hypot(u - 31.5, v - 23.5) / 100.0)
    expected = plain * np.cos(theta) ** 4
    ok = (plain > 20) & (plain < 255)
    assert ok.mean() > 0.5
    assert np.all(np.abs(vig - expected)[ok] <= 1.0)  # both rounded to whole DN
    corner = np.cos(np.arctan(np.hypot(31.5, 23.5) / 100.0)) ** 4
    np.testing.assert_allclose(corner, 0.750, atol=1e-3)
    assert np.all(np.abs(vig[0, 0] - corner * plain[0, 0]) <= 1.0)
    # the per-frame settings scale the frame by exposure x gain
    bright = np.asarray(ae[1], np.float64)
    sel = plain < 80
    assert np.all(np.abs(bright[sel] - 3.0 * plain[sel]) <= 2.0)


def test_auto_exposure_recovers_a_brightness_step_with_its_time_constant():
    """A settled AE loop: the scene darkens 2x; frame k's exposure comes from frame k-1, so
    the log brightness error decays as exp(-t / tau) from the frame after the step (exactly,
    unsaturated); a 3x brighter scene (partly clipped) converges too, and a very dark one
    runs the exposure to its limit and then the gain."""
    model = SN.SensorModel(exposure_s=5e-3)
    ae = AE.AutoExposure()
    dt, tau = 0.05, ae.time_constant_s
    L0 = ae.target_dn / model.mean_dn(1.0)  # the target at 5 ms, gain 1
    rng = np.random.default_rng(0)
    texture = rng.uniform(0.5, 1.5, (20, 30))
    texture /= texture.mean()

    def run(scale, frames=60, step=10):
        metering = np.stack([L0 * texture * (1.0 if k < step else scale)
                             for k in range(frames)])
        exposure, gain = AE.exposure_schedule(metering, dt, model, ae)
        dn = np.array([AE.metered_dn(m, e, g, model)
                       for m, e, g in zip(metering, exposure, gain, strict=True)])
        return exposure, gain, dn

    exposure, gain, dn = run(0.5)
    np.testing.assert_allclose(dn[:10], ae.target_dn, rtol=1e-9)  # settled before the step
    err = np.log(ae.target_dn / dn)
    np.testing.assert_allclose(err[10], np.log(2.0), rtol=1e-9)
    frames_per_tau = round(tau / dt)  # 3 frames
    np.testing.assert_allclose(err[10 + frames_per_tau], np.exp(-1.0) * np.log(2.0),
                               rtol=1e-6)
    assert np.all(np.diff(err[10:]) < 0) and err[-1] < 1e-3
    np.testing.assert_allclose(exposure[-1], 10e-3, rtol=1e-3)  # twice as long, still gain 1
    assert np.all(gain == 1.0)
    # brighter: clipped metering slows the first frames, then it settles at the target
    _, _, dn_up = run(3.0)
    assert dn_up[10] > 200 and abs(dn_up[-1] - ae.target_dn) < 0.01 * ae.target_dn
    # darker than the longest exposure reaches: the gain takes over, capped at MAX_GAIN
    exposure_dark, gain_dark, dn_dark = run(0.1)
    assert exposure_dark[-1] == pytest.approx(ae.max_exposure_s)
    assert gain_dark[-1] == pytest.approx(ae.max_gain)
    assert 0.5 * ae.target_dn < dn_dark[-1] < ae.target_dn
    # a recording starts with the camera's AE already settled (the sensor's own 2 ms is 2.5x
    # too dark): the first frame is at the target; not settled, it converges from 2 ms
    dim = SN.SensorModel(exposure_s=2e-3)
    still = np.stack([L0 * texture] * 5)
    for settled, first in ((True, ae.target_dn), (False, 0.4 * ae.target_dn)):
        e, g = AE.exposure_schedule(still, dt, dim, AE.AutoExposure(start_settled=settled))
        assert AE.metered_dn(still[0], e[0], g[0], dim) == pytest.approx(first, rel=1e-6)
    # the EuRoC preset is the default, valid, and reaches the frame renderer
    euroc = SimConfig(**EUROC_CAMERA_PRESET)
    euroc.validate()
    effects = camera_effects(euroc)
    assert effects.auto_exposure and effects.vignetting > 0 and effects.line_delay_s == 0
    assert camera_effects(SimConfig()) == effects
    ideal = SimConfig(**IDEAL_SENSORS)
    assert camera_effects(ideal) == CameraEffects(
        sensor=sensor_model(ideal), noise=True, blur_samples=5)  # every effect off


def _sliding(speed: float) -> Trajectory:
    """A body moving along world x at ``speed`` m/s, axes = world's (camera looks along +z)."""
    t = np.linspace(0.0, 0.2, 201)
    q = np.zeros((len(t), 4))
    q[:, 0] = 1.0
    p = np.zeros((len(t), 3))
    p[:, 0] = speed * t
    return Trajectory.from_samples(t, p, q)


def test_rolling_shutter_shears_a_vertical_edge_and_is_global_at_zero_delay():
    """Moving sideways at v past a plane at depth d, row r of a rolling shutter is exposed
    (r - (H - 1)/2) * delay after the middle row, so a vertical edge shifts by -f v t_r / d
    pixels in it; with no delay the per-row warp is the global shutter's exactly."""
    image = np.zeros((48, 64))
    image[:, 32:] = 1.0
    speed, depth, delay, f = 2.0, 2.0, 1e-3, 100.0
    traj, t_ns, span = _sliding(speed), np.array([100_000_000]), (0, 200_000_000)
    b = R.ray_bundle(LENS)

    def warp(rel):
        return np.asarray(MB.blur_image(jnp.asarray(image, jnp.float32), jnp.full((48, 64), depth),
                                        jnp.asarray(b.rx), jnp.asarray(b.ry), jnp.asarray(rel),
                                        LENS))

    rolling = sub_exposure_poses(traj, t_ns, np.eye(4), 5e-3, 1, span, delay, 48)[0]
    assert rolling.shape == (1, 48, 4, 4)
    out = warp(rolling)
    edge = (1.0 - out).sum(axis=1) - 0.5  # where each row crosses 0.5 (31.5 unshifted)
    t_row = (np.arange(48) - 23.5) * delay
    np.testing.assert_allclose(edge, 31.5 - f * speed * t_row / depth, atol=0.02)
    assert edge[0] - edge[-1] == pytest.approx(f * speed * 47 * delay / depth, abs=0.03)
    # zero delay (a delay that rounds to 0 ns): per-row poses all equal the global one, and
    # the per-row warp gives the global shutter's frame, with blur
    still = sub_exposure_poses(traj, t_ns, np.eye(4), 5e-3, 3, span, 1e-13, 48)[0]
    glob = sub_exposure_poses(traj, t_ns, np.eye(4), 5e-3, 3, span)[0]
    assert still.shape == (3, 48, 4, 4)
    np.testing.assert_array_equal(still, np.broadcast_to(glob[:, None], still.shape))
    np.testing.assert_array_equal(warp(still), warp(glob))
    assert np.any(warp(glob) != image)  # the blur is there
