"""The IMU noise model: one dataclass that the readers produce, the simulator draws from and
the preintegration propagates.

Units are those of Kalibr's and EuRoC's ``imu0/sensor.yaml`` (the key names there are
``gyroscope_noise_density`` ... ; :mod:`uavcal_jax.data.yaml_io` maps them to these fields).
The discrete covariance of one sample held for ``dt`` is ``density^2 / dt`` (the convention
of GTSAM, Forster et al. and Kalibr).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["ImuNoise", "EUROC_ADIS16448"]


@dataclasses.dataclass(frozen=True)
class ImuNoise:
    """White-noise and random-walk densities of an IMU; the defaults are the EuRoC MAV's
    ADIS16448 (its ``imu0/sensor.yaml``).

    Each value is a scalar (same on all three axes) or a (3,) per-axis array; the axes are
    independent. A registered pytree (every field is a leaf), so it can be passed straight
    into jitted, vmapped or differentiated functions.

    Attributes:
        gyro_noise_density: rad/s/sqrt(Hz). GTSAM's ``setGyroscopeCovariance`` takes its square.
        accel_noise_density: m/s^2/sqrt(Hz). ``setAccelerometerCovariance`` takes its square.
        gyro_random_walk: rad/s^2/sqrt(Hz) (bias diffusion); 0 = constant bias.
        accel_random_walk: m/s^3/sqrt(Hz); 0 = constant bias.
        integration_covariance: GTSAM's ``integrationCovariance`` (its diagonal): position
            variance added per second of integration, m^2/s. Not part of a ``sensor.yaml``;
            0 by default (as in the checks against GTSAM).
    """

    gyro_noise_density: Any = 1.6968e-4
    accel_noise_density: Any = 2.0e-3
    gyro_random_walk: Any = 1.9393e-5
    accel_random_walk: Any = 3.0e-3
    integration_covariance: Any = 0.0

    def variances(self, dtype) -> dict[str, tuple[Any, Any, Any]]:
        """Per-axis variance densities as 3-tuples of scalars of ``dtype`` (for the kernel)."""

        def axes(x, square=True):
            x = jnp.asarray(x, dtype=dtype)
            x = x * x if square else x
            if x.ndim == 0:
                return (x, x, x)
            if x.shape != (3,):
                raise ValueError(f"noise values must be scalars or (3,) arrays, got {x.shape}")
            return (x[0], x[1], x[2])

        return {
            "gyro": axes(self.gyro_noise_density),
            "accel": axes(self.accel_noise_density),
            "gyro_rw": axes(self.gyro_random_walk),
            "accel_rw": axes(self.accel_random_walk),
            "integration": axes(self.integration_covariance, square=False),
        }


jax.tree_util.register_dataclass(
    ImuNoise,
    data_fields=[f.name for f in dataclasses.fields(ImuNoise)],
    meta_fields=[],
)

#: The EuRoC MAV's ADIS16448 noise model (the defaults, named).
EUROC_ADIS16448 = ImuNoise()
