"""IMU preintegration as a ``lax.scan``, interval cutting, prediction and the IMU residual.

Public API::

    preintegrate(dt, gyro, accel, bias_gyro, bias_accel, *, mask, noise, offset, scheme,
                 bias_covariance) -> Preintegrated
    bias_correct(pim, bias_gyro, bias_accel) -> (delta_R, delta_v, delta_p)
    predict(state_i, pim, bias) -> NavState
    imu_residual / imu_residual_whitened / residual_covariance
    interval_samples / interval_batch  (cut [t_i, t_j] from a stream)
    add_offset / remove_offset
    ImuNoise, EUROC_ADIS16448  (the noise model, also what the readers and the simulator use)

See :mod:`uavcal_jax.imu.preintegration` for the schemes, orders and the bad-input policy.
"""

from uavcal_jax.imu.interval import (
    ImuInterval,
    interval_batch,
    interval_capacity,
    interval_samples,
)
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise
from uavcal_jax.imu.offset import add_offset, remove_offset, split_offset
from uavcal_jax.imu.preintegration import (
    SCHEMES,
    THETA_LIMIT,
    Preintegrated,
    bias_correct,
    preintegrate,
)
from uavcal_jax.imu.residual import (
    ImuBias,
    NavState,
    imu_residual,
    imu_residual_whitened,
    predict,
    residual_covariance,
)

__all__ = [
    "EUROC_ADIS16448",
    "SCHEMES",
    "THETA_LIMIT",
    "ImuBias",
    "ImuInterval",
    "ImuNoise",
    "NavState",
    "Preintegrated",
    "add_offset",
    "bias_correct",
    "imu_residual",
    "imu_residual_whitened",
    "interval_batch",
    "interval_capacity",
    "interval_samples",
    "predict",
    "preintegrate",
    "remove_offset",
    "residual_covariance",
    "split_offset",
]
