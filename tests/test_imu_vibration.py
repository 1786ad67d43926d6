"""The simulated IMU's errors beyond noise: rotor vibration (a measured spectrum reproduced),
scale and misalignment, g-sensitivity, and the camera-IMU time offset."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from conftest import SHARED_DATA

from uavcal_jax.config import ConfigError, apply_overrides
from uavcal_jax.geometry.frames import GRAVITY
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise
from uavcal_jax.sim.config import EUROC_IMU_REALISM, IMU_ERRORS, SimConfig
from uavcal_jax.sim.flights import procedural_flight
from uavcal_jax.sim.imu_synth import ImuIntrinsics, synthesize_imu
from uavcal_jax.sim.imu_vibration import (
    EUROC_V101_REST_VIBRATION,
    EUROC_V101_VIBRATION,
    VibrationBand,
    VibrationSpectrum,
    fit_vibration,
    fit_vibration_file,
    imu_psd,
    rest_weight,
    vibration_samples,
)
from uavcal_jax.sim.simulate import imu_error_options
from uavcal_jax.sim.trajectory import Trajectory

RATE = 200.0
MICRO = SHARED_DATA / "euroc_v101_micro"
QUIET = ImuNoise(gyro_noise_density=1e-5, accel_noise_density=1e-4, gyro_random_walk=0.0,
                 accel_random_walk=0.0)


def _band_power(x: np.ndarray, lo: float, hi: float, nperseg: int = 1024) -> np.ndarray:
    f, p = imu_psd(x, RATE, nperseg)
    m = (f >= lo) & (f < hi)
    return p[m].sum(axis=0) * (f[1] - f[0])


def test_vibration_reproduces_a_psd_peak_and_is_fitted_back():
    band = VibrationBand(freq_hz=37.3, sigma_hz=0.6, gyro_rms=(0.01, 0.0, 0.02),
                         accel_rms=(0.3, 0.1, 0.05))
    spec = VibrationSpectrum(bands=(band,), gyro_floor=(2e-4,) * 3, accel_floor=(0.01,) * 3,
                             f_low_hz=15.0, rate_hz=RATE)
    gyro, accel = vibration_samples(spec, 24000, RATE, np.random.default_rng(3))
    x = np.concatenate([gyro, accel], axis=1)
    f, p = imu_psd(x, RATE)
    df = f[1] - f[0]
    peak = f[np.argmax(p[:, 3])]
    assert abs(peak - band.freq_hz) <= df
    expected = np.square(band.gyro_rms + band.accel_rms)
    floors = 2 * np.square(spec.gyro_floor + spec.accel_floor)
    measured = _band_power(x, 33.0, 41.5) - floors * 8.5
    np.testing.assert_allclose(measured, expected, rtol=0.2, atol=2e-5)
    # the fit finds the band where it was put, with its power, and the floors
    fit = fit_vibration(gyro, accel, RATE, QUIET)
    assert len(fit.bands) == 1
    assert abs(fit.bands[0].freq_hz - band.freq_hz) <= df
    assert fit.bands[0].accel_rms[0] ** 2 == pytest.approx(band.accel_rms[0] ** 2, rel=0.2)
    # what the fit leaves as floor (a low percentile) it counts in the band: the model's power
    # above f_low, bands plus floors, is the samples' (whose band power is random to ~15 %)
    def model_power(s):
        floors = 2 * np.square(s.gyro_floor + s.accel_floor) * (RATE / 2 - s.f_low_hz)
        return floors + sum(np.square(b.gyro_rms + b.accel_rms) for b in s.bands)

    np.testing.assert_allclose(model_power(fit), _band_power(x, 15.0, RATE / 2 + 1), rtol=0.05)


def test_vibration_scale_and_seed():
    a = vibration_samples(EUROC_V101_VIBRATION, 4000, RATE, np.random.default_rng(0), 2.0)
    b = vibration_samples(EUROC_V101_VIBRATION, 4000, RATE, np.random.default_rng(0), 1.0)
    np.testing.assert_allclose(a[1], 2.0 * b[1], rtol=1e-12, atol=1e-15)


@pytest.mark.skipif(not MICRO.is_dir(), reason="needs ../shared/data/euroc_v101_micro")
def test_euroc_v101_constant_is_the_measured_spectrum_and_sim_matches_real_band_power():
    from uavcal_jax.data.euroc import read_imu_folder

    fit = fit_vibration_file(MICRO)
    const = EUROC_V101_VIBRATION
    assert len(fit.bands) == len(const.bands)
    for got, want in zip(fit.bands, const.bands, strict=True):
        np.testing.assert_allclose([got.freq_hz, got.sigma_hz, *got.gyro_rms, *got.accel_rms],
                                   [want.freq_hz, want.sigma_hz, *want.gyro_rms,
                                    *want.accel_rms], rtol=1e-3)
    np.testing.assert_allclose(fit.gyro_floor + fit.accel_floor,
                               const.gyro_floor + const.accel_floor, rtol=1e-3)
    # real band power above 15 Hz vs the simulator's (vibration + EuRoC's white noise)
    imu, _ = read_imu_folder(MICRO / "mav0" / "imu0")
    real = np.concatenate([imu.gyro, imu.accel], axis=1)
    n = len(real)
    gyro, accel = vibration_samples(const, n, RATE, np.random.default_rng(7))
    white = np.random.default_rng(8).normal(size=(n, 6)) * math.sqrt(RATE) * np.array(
        [EUROC_ADIS16448.gyro_noise_density] * 3 + [EUROC_ADIS16448.accel_noise_density] * 3)
    sim = np.concatenate([gyro, accel], axis=1) + white
    np.testing.assert_allclose(_band_power(sim, 15.0, 100.0), _band_power(real, 15.0, 100.0),
                               rtol=0.1)


def _stand_then_fly(stand_s: float = 6.0, fly_s: float = 14.0) -> Trajectory:
    """A MAV standing ``stand_s`` seconds, then flying a 1 m circle at 0.5 Hz."""
    t = np.arange(0.0, stand_s + fly_s, 0.01)
    phase = 2 * np.pi * 0.5 * np.clip(t - stand_s, 0.0, None)
    ramp = np.clip((t - stand_s) / 2.0, 0.0, 1.0) ** 2  # eases into the circle
    pos = np.stack([ramp * np.sin(phase), ramp * (1 - np.cos(phase)), 0.5 * ramp], axis=1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    return Trajectory.from_samples(t, pos, q)


def test_rest_weight_tells_standing_from_flight_and_ramps():
    t = np.arange(0.0, 6.0, 1 / RATE)
    pos = np.zeros((len(t), 3))
    pos[:, 2] = np.where(t > 3.0, 0.3 * (t - 3.0), 0.0)  # still 3 s, then climbing 0.3 m/s
    pos += np.random.default_rng(0).normal(scale=5e-4, size=pos.shape)  # mocap jitter
    w = rest_weight(pos, np.zeros_like(pos), RATE)
    assert np.all(w[t < 2.2] == 1.0) and np.all(w[t > 3.0] == 0.0)
    ramp = w[(t > 2.2) & (t < 3.0)]
    assert np.all(np.diff(ramp) <= 0) and 0 < ramp.mean() < 1  # spools up before lift-off
    # turning in place is not rest
    spin = np.tile([0.0, 0.0, 0.3], (len(t), 1))
    assert not rest_weight(np.zeros_like(pos), spin, RATE).any()


def test_rest_vibration_switches_spectrum_and_never_resting_changes_nothing():
    traj = _stand_then_fly()
    imu = synthesize_imu(traj, RATE, vibration=EUROC_V101_VIBRATION,
                         rest_vibration=EUROC_V101_REST_VIBRATION, seed=3).imu
    exact = synthesize_imu(traj, RATE).imu
    err = np.concatenate([imu.gyro - exact.gyro, imu.accel - exact.accel], axis=1)
    t = (imu.t_ns - imu.t_ns[0]) * 1e-9
    standing, flying = err[t < 5.0], err[t > 7.0]
    for x, spec in ((standing, EUROC_V101_REST_VIBRATION), (flying, EUROC_V101_VIBRATION)):
        f, p = imu_psd(x, RATE, 256)
        band = f >= 15.0
        tallest = max(spec.bands, key=lambda b: b.accel_rms[1] ** 2 / b.sigma_hz)
        assert abs(f[band][np.argmax(p[band, 4])] - tallest.freq_hz) < 3.0  # accel y's peak
    # standing, the accelerometer vibrates about a third as much as in flight
    ratio = _band_power(standing, 15.0, 100.0)[3:].sum() / _band_power(flying, 15.0, 100.0)[
        3:].sum()
    assert 0.05 < ratio < 0.3
    # a flight that never rests reads exactly what it reads without the rest spectrum
    t_ns = 7_000_000_000 + 5_000_000 * np.arange(2000, dtype=np.int64)  # the circle alone
    state = traj.state_ns(t_ns)
    assert not rest_weight(state.position, state.angular_velocity_body, RATE).any()
    a = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=4, t_ns=t_ns,
                       vibration=EUROC_V101_VIBRATION, rest_vibration=EUROC_V101_REST_VIBRATION)
    b = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=4, t_ns=t_ns,
                       vibration=EUROC_V101_VIBRATION)
    np.testing.assert_array_equal(a.imu.accel, b.imu.accel)


def test_rest_vibration_applies_to_recorded_flights_only():
    planned = imu_error_options(SimConfig())
    recorded = imu_error_options(SimConfig(trajectory="flight.txt"))
    assert planned["rest_vibration"] is None  # a planned flight's still hover is in flight
    assert recorded["rest_vibration"] is EUROC_V101_REST_VIBRATION
    assert imu_error_options(SimConfig(), recorded=True)["rest_vibration"] is not None
    off = SimConfig(trajectory="flight.txt", imu_rest_vibration=False)
    assert imu_error_options(off)["rest_vibration"] is None
    assert imu_error_options(dataclasses.replace(off, imu_vibration=0.0))["vibration"] is None


@pytest.mark.skipif(not MICRO.is_dir(), reason="needs ../shared/data/euroc_v101_micro")
def test_euroc_v101_rest_constant_is_measured_and_sim_matches_the_standing_imu():
    from uavcal_jax.data.euroc import read_euroc
    from uavcal_jax.sim.realism import imu_errors

    fit = fit_vibration_file(MICRO, rest=True)
    const = EUROC_V101_REST_VIBRATION
    assert len(fit.bands) == len(const.bands)
    for got, want in zip(fit.bands, const.bands, strict=True):
        np.testing.assert_allclose([got.freq_hz, got.sigma_hz, *got.gyro_rms, *got.accel_rms],
                                   [want.freq_hz, want.sigma_hz, *want.gyro_rms,
                                    *want.accel_rms], rtol=1e-3)
    # the simulator along V1_01's own ground truth: its standing seconds vibrate as the real
    # IMU's did (band power above 15 Hz per axis), its flight as the flight did
    seq = read_euroc(MICRO)
    errors = imu_errors(seq.ground_truth, seq.imu, EUROC_ADIS16448, 0,
                        **imu_error_options(SimConfig(), recorded=True))
    t = (errors["t_ns"] - errors["t_ns"][0]) * 1e-9
    standing = t < 4.4  # at rest (the constant's span)
    for name in ("real", "sim"):
        errors[name] = errors[name][standing]
    real = _band_power(errors["real"], 15.0, 100.0, 256)
    sim = _band_power(errors["sim"], 15.0, 100.0, 256)
    # 4.4 s of humps a few Hz wide: each axis's band power is random to about 25 %
    np.testing.assert_allclose(sim[3:], real[3:], rtol=0.4)
    assert sim[3:].sum() == pytest.approx(real[3:].sum(), rel=0.3)
    # the flight's spectrum there would be 4x the power
    flight = _band_power(vibration_samples(EUROC_V101_VIBRATION, standing.sum(), RATE,
                                           np.random.default_rng(0))[1], 15.0, 100.0, 256)
    assert flight.sum() > 2.5 * real[3:].sum()


def test_scale_and_misalignment_on_a_known_input():
    intr = ImuIntrinsics.from_errors(scale=(0.001, -0.002, 0.003, 0.01, 0.02, 0.03),
                                     misalignment=(1e-3, 2e-3, 3e-3, 0.1, 0.2, 0.3))
    w = np.array([[0.5, -1.0, 2.0]])
    a = np.array([[1.0, 2.0, 3.0]])
    gyro, accel = intr.apply(w, a)
    np.testing.assert_allclose(accel[0], [1.01 * 1, 0.1 * 1 + 1.02 * 2,
                                          0.2 * 1 + 0.3 * 2 + 1.03 * 3], rtol=1e-12)
    np.testing.assert_allclose(gyro[0], [1.001 * 0.5, 1e-3 * 0.5 - 0.998 * 1.0,
                                         2e-3 * 0.5 - 3e-3 * 1.0 + 1.003 * 2.0], rtol=1e-12)
    # OpenVINS's "kalibr" model: D = T^-1 is lower triangular too
    assert np.allclose(np.triu(np.linalg.inv(intr.T_a), 1), 0.0)


def test_g_sensitivity_of_a_static_imu():
    t = np.linspace(0.0, 4.0, 401)
    roll = math.radians(25.0)
    q = np.tile([math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0], (len(t), 1))
    still = Trajectory.from_samples(t, np.zeros((len(t), 3)), q)
    T_g = np.arange(1.0, 10.0) * 1e-5
    intr = ImuIntrinsics.from_errors(g_sensitivity=T_g)
    imu = synthesize_imu(still, RATE, t_start=1.0, t_end=3.0, intrinsics=intr).imu
    f = np.array([0.0, GRAVITY * math.sin(roll), GRAVITY * math.cos(roll)])
    np.testing.assert_allclose(imu.accel, np.tile(f, (len(imu), 1)), atol=1e-9)
    np.testing.assert_allclose(imu.gyro, np.tile(T_g.reshape(3, 3) @ f, (len(imu), 1)),
                               atol=1e-11)


def test_time_offset_delays_the_imu_by_the_shift():
    traj = procedural_flight(4, 12.0)
    t_ns = 1_000_000_000 + 5_000_000 * np.arange(2000, dtype=np.int64)
    ref = synthesize_imu(traj, RATE, t_ns=t_ns).imu
    late = synthesize_imu(traj, RATE, t_ns=t_ns, time_offset=0.02).imu  # 4 samples
    np.testing.assert_array_equal(late.t_ns, ref.t_ns)
    np.testing.assert_allclose(late.gyro[4:], ref.gyro[:-4], atol=1e-12)
    # cross-correlation of the angular rate peaks at +4 samples (IMU stamps late)
    x, y = ref.gyro[:, 2] - ref.gyro[:, 2].mean(), late.gyro[:, 2] - late.gyro[:, 2].mean()
    lags = np.arange(-10, 11)
    xc = [np.dot(x[20:-20], np.roll(y, -k)[20:-20]) for k in lags]
    assert lags[int(np.argmax(xc))] == 4
    # beyond the flight's span, the first state is read
    early = synthesize_imu(traj, RATE, t_start=0.0, t_end=1.0, time_offset=0.01).imu
    np.testing.assert_allclose(early.gyro[0], early.gyro[1], atol=1e-12)


def test_options_are_a_pure_function_of_the_seed_and_off_changes_nothing():
    traj = procedural_flight(2, 6.0)
    intr = ImuIntrinsics.from_errors(*(EUROC_IMU_REALISM[k] for k in (
        "imu_scale", "imu_misalignment", "imu_g_sensitivity")))
    opts = dict(vibration=EUROC_V101_VIBRATION, intrinsics=intr, time_offset=0.003)
    a = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=9, **opts)
    b = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=9, **opts)
    np.testing.assert_array_equal(a.imu.accel, b.imu.accel)
    base = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=9)
    off = synthesize_imu(traj, RATE, EUROC_ADIS16448, seed=9, vibration=EUROC_V101_VIBRATION,
                         vibration_scale=0.0, intrinsics=None, time_offset=0.0)
    np.testing.assert_array_equal(off.imu.gyro, base.imu.gyro)
    # the vibration has its own stream: the biases are those of the run without it
    np.testing.assert_array_equal(a.bias_gyro, base.bias_gyro)


def test_config_fields_parse_validate_and_preset():
    config = apply_overrides(SimConfig(), ["imu_scale=0.001,0,0,0,0,-0.002",
                                           "imu_time_offset=0.004", "imu_vibration=1"])
    assert config.imu_scale == (0.001, 0.0, 0.0, 0.0, 0.0, -0.002)
    assert config.to_dict()["imu_scale"] == list(config.imu_scale)
    config.validate()
    assert set(EUROC_IMU_REALISM) == set(IMU_ERRORS)
    realistic = dataclasses.replace(SimConfig(), **EUROC_IMU_REALISM)
    realistic.validate()
    with pytest.raises(ValueError, match="imu_g_sensitivity"):
        SimConfig(imu_g_sensitivity=(0.0,) * 6).validate()
    with pytest.raises(ValueError, match="imu_vibration"):
        SimConfig(imu_vibration=-1.0).validate()
    with pytest.raises(ConfigError):
        apply_overrides(SimConfig(), ["imu_time_offset=soon"])


@pytest.mark.filterwarnings("ignore::uavcal_jax.errors.DataRepairWarning")  # the slice's cam1
def test_hybrid_refuses_simulated_imu_errors(euroc_micro, tmp_path):
    from uavcal_jax.sim.hybrid import simulate_hybrid

    with pytest.raises(ValueError, match="imu_time_offset do not apply"):
        simulate_hybrid(euroc_micro, tmp_path / "h", SimConfig(imu_time_offset=0.002,
                                                                frames=False), duration=1.0)
