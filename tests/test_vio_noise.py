"""The VIO's IMU noise model: the recording's densities raised to the configured floors."""

from __future__ import annotations

import numpy as np
import pytest

from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise
from uavcal_jax.vio.config import VioConfig, imu_noise


def test_floors_raise_the_white_noise_only_where_it_is_lower():
    recorded = ImuNoise(gyro_noise_density=np.array([1e-4, 5e-3, 2e-4]),
                        accel_noise_density=0.05)
    used = imu_noise(VioConfig(min_gyro_noise_density=2e-3, min_accel_noise_density=0.01),
                     recorded)
    np.testing.assert_allclose(used.gyro_noise_density, [2e-3, 5e-3, 2e-3])
    assert used.accel_noise_density == 0.05  # already above its floor
    # the random walks are the bias model, not the vibration's: kept
    assert used.gyro_random_walk == recorded.gyro_random_walk
    assert used.accel_random_walk == recorded.accel_random_walk


def test_zero_floors_keep_the_recordings_model():
    assert imu_noise(VioConfig(min_gyro_noise_density=0.0, min_accel_noise_density=0.0),
                     EUROC_ADIS16448) == EUROC_ADIS16448


def test_a_negative_floor_is_refused():
    with pytest.raises(ValueError, match="floors"):
        VioConfig(min_accel_noise_density=-1.0)
