"""Offset injection (section 3.4, eq. 12): the draws follow the configured distribution,
a validation set shares one offset, and injection adds offsets to real samples only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib.config import InjectionConfig
from uavcal_jax.calib.inject import (
    ImuStats,
    imu_statistics,
    inject,
    offset_moments,
    training_offsets,
    validation_offsets,
)
from uavcal_jax.data.windows import WindowConfig, WindowSet

N = 20_000  # draws: relative standard error of a std estimate ~ 0.5 %
STATS = ImuStats(jnp.asarray([0.1, -0.2, 0.0, 0.3, 0.1, 9.8], jnp.float32),
                 jnp.asarray([0.5, 0.4, 0.3, 1.5, 1.0, 2.0], jnp.float32))


def _draw(config):
    return np.asarray(training_offsets(jax.random.key(0), config, STATS, N))


def test_paper_protocol_is_normal_with_n_m_times_the_variance():
    o = _draw(InjectionConfig(protocol="paper", noise_multiplier=2.0))
    mean, std = np.asarray(STATS.mean), np.asarray(STATS.std)
    np.testing.assert_allclose(o.mean(axis=0), mean, atol=4 * np.sqrt(2) * std.max() / np.sqrt(N))
    np.testing.assert_allclose(o.std(axis=0), np.sqrt(2.0) * std, rtol=0.03)
    # draws are independent per sample and per channel
    assert abs(np.corrcoef(o[:, 0], o[:, 1])[0, 1]) < 0.05
    assert len(np.unique(o[:, 0])) > 0.99 * N  # a new offset per sample (float32 ties aside)


def test_symmetric_protocol_is_uniform_on_plus_minus_n_m_sigma():
    o = _draw(InjectionConfig(protocol="symmetric", noise_multiplier=3.0))
    half = 3.0 * np.asarray(STATS.std)
    assert np.all(np.abs(o) <= half + 1e-6)
    np.testing.assert_allclose(np.abs(o).max(axis=0), half, rtol=0.01)
    np.testing.assert_allclose(o.std(axis=0), half / np.sqrt(3.0), rtol=0.03)
    np.testing.assert_allclose(o.mean(axis=0), 0.0, atol=4 * half.max() / np.sqrt(3 * N))


def test_physical_protocol_uses_the_configured_ranges():
    cfg = InjectionConfig(protocol="physical", gyro_range=0.08, accel_range=0.16)
    o = _draw(cfg)
    np.testing.assert_allclose(np.abs(o).max(axis=0), [0.08] * 3 + [0.16] * 3, rtol=0.01)
    # per-axis U(-r, r): RMS norm r, the EuRoC bias sizes
    np.testing.assert_allclose(np.sqrt(np.mean(np.sum(o[:, :3] ** 2, axis=1))), 0.08, rtol=0.02)
    np.testing.assert_allclose(np.sqrt(np.mean(np.sum(o[:, 3:] ** 2, axis=1))), 0.16, rtol=0.02)


@pytest.mark.parametrize("protocol", ["paper", "symmetric", "physical"])
def test_offset_moments_are_those_of_the_draws(protocol):
    """The standardised model predicts in these units: they must be the draws' moments."""
    cfg = InjectionConfig(protocol=protocol, noise_multiplier=3.0)
    o = _draw(cfg)
    mean, std = (np.asarray(x) for x in offset_moments(cfg, STATS))
    np.testing.assert_allclose(o.std(axis=0), std, rtol=0.03)
    np.testing.assert_allclose(o.mean(axis=0), mean, atol=4 * std.max() / np.sqrt(N))


def test_validation_offset_is_constant_over_the_set():
    o = np.asarray(validation_offsets(jax.random.key(5), InjectionConfig(), STATS, 50))
    assert o.shape == (50, 6)
    assert np.all(o == o[0]) and np.any(o[0] != 0)
    other = np.asarray(validation_offsets(jax.random.key(6), InjectionConfig(), STATS, 50))
    assert np.all(other[0] != o[0])  # another trial, another offset


def test_inject_adds_to_real_samples_only():
    rng = np.random.default_rng(0)
    imu = rng.normal(size=(3, 5, 6)).astype(np.float32)
    mask = np.ones((3, 5), bool)
    mask[1, 3:] = False
    imu[~mask] = 0
    off = rng.normal(size=(3, 6)).astype(np.float32)
    got = np.asarray(inject(imu, off, mask))
    want = np.where(mask[..., None], imu + off[:, None, :], 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    three = np.asarray(inject(imu[..., :3], off[:, :3]))
    np.testing.assert_allclose(three, imu[..., :3] + off[:, None, :3], rtol=1e-6)


def _window_set(gyro, accel, imu_range):
    n = gyro.shape[0]
    return WindowSet(config=WindowConfig(), name="synthetic",
                     frames=np.zeros((1, 2, 2), np.uint8), frame_t_ns=np.zeros(1, np.int64),
                     imu_index=np.zeros(1, np.int32), imu_t_ns=np.arange(n, dtype=np.int64),
                     gyro=gyro, accel=accel, start_ns=np.zeros(len(imu_range), np.int64),
                     frame_index=np.zeros((len(imu_range), 1), np.int32),
                     frame_mask=np.ones((len(imu_range), 1), bool),
                     imu_range=np.asarray(imu_range, np.int64))


def test_statistics_from_windows_and_arrays():
    rng = np.random.default_rng(1)
    gyro, accel = rng.normal(0, 0.3, (100, 3)), rng.normal(9.8, 1.0, (100, 3))
    ws = _window_set(gyro, accel, [(10, 40), (30, 60)])  # overlapping: samples 10..59 once
    s = imu_statistics(ws)
    both = np.concatenate([gyro, accel], axis=1)[10:60]
    np.testing.assert_allclose(np.asarray(s.mean), both.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(s.std), both.std(axis=0), rtol=1e-5)
    s2 = imu_statistics([ws, _window_set(gyro, accel, [(70, 80)])])
    both2 = np.concatenate([both, np.concatenate([gyro, accel], axis=1)[70:80]])
    np.testing.assert_allclose(np.asarray(s2.std), both2.std(axis=0), rtol=1e-5)
    windows = both.reshape(5, 10, 6)
    mask = np.ones((5, 10), bool)
    mask[4] = False
    s3 = imu_statistics(windows, mask)
    np.testing.assert_allclose(np.asarray(s3.mean), both[:40].mean(axis=0), rtol=1e-5)
    with pytest.raises(ValueError, match="no IMU samples"):
        imu_statistics(windows, np.zeros((5, 10), bool))
