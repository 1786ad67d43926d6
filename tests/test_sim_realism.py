"""The realism statistics (``experiments/sim_realism.py``): IMU noise statistics
(:mod:`uavcal_jax.imu.noise_stats`), image statistics (:mod:`uavcal_jax.sim.realism`) and the
front end's (:mod:`uavcal_jax.vio.frontend_stats`), against analytic references."""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from uavcal_jax.data.euroc_rig import euroc_calibration
from uavcal_jax.imu import noise_stats
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.sim import realism
from uavcal_jax.vio.frontend import FeatureTracker
from uavcal_jax.vio.frontend_stats import corner_count, lk_pair_stats, tracking_stats

DT = 0.005  # EuRoC's 200 Hz


def test_allan_of_white_noise_gives_its_density():
    q = 2e-3  # unit/sqrt(Hz)
    x = np.random.default_rng(0).normal(size=(200_000, 3)) * q / np.sqrt(DT)
    taus, adev = noise_stats.allan_deviation(x, DT)
    assert adev.shape == (len(taus), 3)
    short = taus <= 10.0
    np.testing.assert_allclose(adev[short], np.broadcast_to(
        (q / np.sqrt(taus[short]))[:, None], adev[short].shape), rtol=0.08)
    np.testing.assert_allclose(noise_stats.white_noise_density(taus, adev), q, rtol=0.03)


def test_allan_of_a_random_walk_rises_as_sqrt_tau_over_3():
    k = 1e-3  # unit/s/sqrt(Hz): ADEV(tau) = k sqrt(tau / 3) (IEEE 952)
    x = np.cumsum(np.random.default_rng(1).normal(size=(400_000, 4)) * k * np.sqrt(DT), axis=0)
    taus, adev = noise_stats.allan_deviation(x, DT, [10.0, 50.0])
    np.testing.assert_allclose(adev.mean(axis=1), k * np.sqrt(taus / 3.0), rtol=0.12)
    # its minimum is at the shortest tau: the bias instability read there is min / 0.664
    _, curve = noise_stats.allan_deviation(x[:, 0], DT, [0.01, 0.1, 1.0])
    assert noise_stats.bias_instability(curve) == pytest.approx(curve[0] / 0.6643, rel=1e-3)


def test_allan_matches_allantools_oadev():
    allantools = pytest.importorskip("allantools")
    x = np.random.default_rng(2).normal(size=5000)
    taus = [0.005, 0.05, 0.5, 5.0]
    ours_t, ours = noise_stats.allan_deviation(x, DT, taus)
    ref_t, ref, _, _ = allantools.oadev(x, rate=1 / DT, data_type="freq", taus=taus)
    np.testing.assert_allclose(ours_t, ref_t)
    np.testing.assert_allclose(ours, ref, rtol=1e-9)


def test_psd_peak_band_power_and_white_level():
    fs, amp, f0, q = 200.0, 0.3, 37.0, 0.01
    t = np.arange(int(120 * fs)) / fs
    rng = np.random.default_rng(3)
    x = amp * np.sin(2 * np.pi * f0 * t) + rng.normal(size=t.size) * q * np.sqrt(fs)
    f, p = noise_stats.power_spectral_density(x, fs)
    assert noise_stats.peak_frequency(f, p, 20.0) == pytest.approx(f0, abs=f[1])
    # white noise of density q (the sensor.yaml convention) is 2 q^2 one-sided; the
    # sinusoid's power amp^2 / 2 lies in a few bins around f0
    assert np.median(p[(f > 50) & (f < 90)]) == pytest.approx(2 * q * q, rel=0.1)
    tone = noise_stats.band_power(f, p, f0 - 2, f0 + 2) - 4.0 * 2 * q * q
    assert tone == pytest.approx(amp * amp / 2, rel=0.05)


def test_noise_summary_of_white_noise():
    q = 1.7e-4
    x = np.random.default_rng(4).normal(size=(40_000, 3)) * q / np.sqrt(DT)
    s = noise_stats.noise_summary(x, DT, taus=(1.0,))
    assert s["white_density"] == pytest.approx(q, rel=0.05)
    assert s["adev_1s"] == pytest.approx(q, rel=0.1)
    # white noise: the band's RMS is sqrt(3 axes * 2 q^2 * (100 - 15) Hz) (one-sided PSD)
    assert s["vibration_rms"] == pytest.approx(q * np.sqrt(3 * 2 * 85.0), rel=0.05)


def _scene(h=120, w=160, seed=5) -> np.ndarray:
    """A smooth textured image, grey levels 40-200."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (h, w)), (0, 0), 6)
    img = (img - img.min()) / (img.max() - img.min())
    return 40 + 160 * img


def test_temporal_noise_of_a_static_scene_gives_its_sigma():
    sigma = 2.0
    scene = _scene()
    scene[:10] = 255.0  # clipped rows carry no noise and must not count
    frames = scene + np.random.default_rng(6).normal(size=(60, *scene.shape)) * sigma
    frames[:, :10] = 255.0
    noise = realism.temporal_noise(frames)
    assert noise["std_median"] == pytest.approx(sigma, rel=0.05)
    assert 40 < noise["mean_level"] < 200


def test_photon_transfer_separates_read_and_shot_noise():
    read, shot = 1.5, 0.04  # grey levels; grey levels^2 per grey level
    scene = np.tile(np.linspace(20, 230, 400), (60, 1))  # every level, flat along rows
    sigma = np.sqrt(read * read + shot * scene)
    frames = scene + np.random.default_rng(8).normal(size=(80, *scene.shape)) * sigma
    ptc = realism.photon_transfer(frames, flat_quantile=1.0)
    assert ptc["levels"] >= 8  # the bins inside LINEAR_RANGE_DN
    assert ptc["read_noise"] == pytest.approx(read, rel=0.1)
    assert ptc["shot_slope"] == pytest.approx(shot, rel=0.1)


def test_intensity_and_gradient_statistics():
    ramp = np.tile(np.arange(100, dtype=np.float64) * 2.0, (50, 1))  # 2 grey levels per px
    np.testing.assert_allclose(realism.gradient_magnitude(ramp), 2.0)
    g = realism.gradient_summary(np.stack([ramp, ramp]))
    assert g == pytest.approx({"mean": 2.0, "p50": 2.0, "p90": 2.0})
    s = realism.intensity_summary(ramp.astype(np.uint8)[None])
    assert s["mean"] == pytest.approx(99.0) and s["p50"] == pytest.approx(99.0)
    assert s["saturated"] == pytest.approx(1 / 100)  # the column at 0
    h = realism.intensity_histogram(ramp.astype(np.uint8))
    assert h.sum() == pytest.approx(1.0) and h[0] == pytest.approx(0.01)
    a, b = np.zeros(256), np.zeros(256)
    a[100], b[130] = 1.0, 5.0
    assert realism.histogram_emd(a, b) == pytest.approx(30.0)
    assert realism.histogram_emd(h, h) == 0.0


def test_front_end_statistics_on_a_shifted_textured_image():
    rng = np.random.default_rng(7)
    big = cv2.GaussianBlur(rng.uniform(0, 255, (520, 800)), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    left = [big[20 + k:500 + k, 20:772] for k in range(3)]  # the scene moves 1 px a frame
    tracker = FeatureTracker(euroc_calibration(0), euroc_calibration(1))
    assert corner_count(tracker, left[0]) > tracker.config.max_features
    lk = lk_pair_stats(tracker, left[0], left[1])
    assert lk["corners"] == tracker.config.max_features
    assert lk["survival"] > 0.95 and lk["fb_px"] < 0.05
    flat = np.full_like(left[0], 128)
    assert corner_count(tracker, flat) == 0
    assert np.isnan(lk_pair_stats(tracker, flat, flat)["survival"])
    track = tracking_stats(tracker, left, None)  # monocular: no stereo match
    assert track["survival"] > 0.95
    assert track["stereo_rate"] == 0.0 and track["tracked"] >= tracker.config.max_features - 5


def test_stereo_matches_says_why_a_corner_is_unmatched():
    """A plane 3 m before a distortion-free rig with an 11 cm baseline: the right image is the
    left shifted by the disparity. Matched where it is; not matched where the right view is
    blank; failing the epipolar check where the right view is shifted off its rows."""
    import dataclasses

    from uavcal_jax.vio.frontend_stats import STEREO_STATUS, stereo_matches

    cam0 = dataclasses.replace(euroc_calibration(0), distortion=np.zeros(4))
    T_01 = np.eye(4)
    T_01[0, 3] = 0.11  # cam1 11 cm along cam0's x
    cam1 = dataclasses.replace(cam0, T_BS=cam0.T_BS @ T_01)
    tracker = FeatureTracker(cam0, cam1)
    rng = np.random.default_rng(3)
    big = cv2.GaussianBlur(rng.uniform(0, 255, (480, 800)), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    d = 17  # px: fx 458 * 0.11 m / 17 px is a plane 2.96 m away
    left, right = big[:, :752], big[:, d:752 + d]
    pts, status = stereo_matches(tracker, left, right)
    assert len(pts) == tracker.config.max_features and set(status) <= set(range(4))
    assert len(STEREO_STATUS) == 4
    inside = (pts[:, 0] > 40) & (pts[:, 0] < 700) & (pts[:, 1] > 30) & (pts[:, 1] < 450)
    assert np.mean(status[inside] == 0) > 0.95
    blank = right.copy()
    blank[:, 376:] = 128
    _, status_b = stereo_matches(tracker, left, blank)
    far_right = pts[:, 0] > 376 + 40
    assert np.mean(status_b[far_right] == 0) < 0.1 and np.all(status_b[far_right] != 3)
    off_rows = np.roll(right, 6, axis=0)  # 6 px off the epipolar line (tolerance 1.5 px)
    _, status_e = stereo_matches(tracker, left, off_rows)
    assert np.mean(status_e[inside] == 3) > 0.9


@pytest.mark.realdata
def test_imu_errors_of_the_real_micro_slice(euroc_micro):
    from uavcal_jax.sim.hybrid import read_real

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = read_real(euroc_micro)
    err = realism.imu_errors(seq.ground_truth, seq.imu, EUROC_ADIS16448, seed=0)
    assert err["real"].shape == err["sim"].shape == (len(err["t_ns"]), 6)
    # standing still (the first 4.7 s), the real error is the sensor's bias: the ground
    # truth's bias columns
    still = err["t_ns"] <= err["t_ns"][0] + 4_500_000_000
    gt_still = seq.ground_truth.t_ns <= err["t_ns"][0] + 4_500_000_000
    np.testing.assert_allclose(err["real"][still, :3].mean(axis=0),
                               seq.ground_truth.bias_gyro[gt_still].mean(axis=0), atol=3e-3)
    # the simulated error is the noise model's
    s = noise_stats.noise_summary(err["sim"][:, :3], DT, taus=(1.0,))
    assert s["white_density"] == pytest.approx(EUROC_ADIS16448.gyro_noise_density, rel=0.1)


def test_the_experiment_without_the_real_data_says_where_and_exits_2(tmp_path, capsys,
                                                                     monkeypatch):
    root = Path(__file__).resolve().parents[1] / "experiments"
    monkeypatch.syspath_prepend(str(root))  # the script imports its folder's _docs
    spec = importlib.util.spec_from_file_location("sim_realism", root / "sim_realism.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    missing = tmp_path / "no_such_folder"
    assert script.main(["--data", str(missing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0]
    assert not (tmp_path / "out").exists()
