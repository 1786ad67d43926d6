"""The least-squares offset of one whole IMU stream against its ground truth: the per-span
reference the calibrator baseline's tests compare :func:`uavcal_jax.calib.baselines.
least_squares_windows` (what the library runs) and scipy's solver against."""

from __future__ import annotations

import jax

from uavcal_jax.calib.baselines import (
    LeastSquaresConfig,
    _check_ground_truth,
    ground_truth_rotations,
    keyframe_pairs,
    least_squares_fit,
)
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise

CONFIG = LeastSquaresConfig()


def least_squares_offset(imu_t_ns, gyro, accel, gt_t_ns, gt_rotation, gt_position, gt_velocity,
                         config: LeastSquaresConfig = CONFIG, *,
                         noise: ImuNoise = EUROC_ADIS16448, span=None,
                         return_std: bool = False):
    """The least-squares constant offset of one IMU stream, (6,) gyro rad/s then accel m/s^2.

    Arguments as :func:`keyframe_pairs`; ``noise`` weights the accel rows and gives the
    predicted standard deviation, a second (6,) array with ``return_std``. Raises
    :class:`DataError` on too few keyframe pairs, bad samples or an invalid preintegration.
    """
    pairs = keyframe_pairs(imu_t_ns, gyro, accel, gt_t_ns, gt_rotation, gt_position,
                           gt_velocity, config, span=span)
    pairs = jax.tree_util.tree_map(lambda x: x[None], pairs)
    offset, std = least_squares_fit(pairs, noise, config)
    return (offset[0], std[0]) if return_std else offset[0]



def sequence_offset(sequence: Sequence, config: LeastSquaresConfig = CONFIG, *,
                    span=None, noise: ImuNoise | None = None, return_std: bool = False):
    """:func:`least_squares_offset` of a :class:`Sequence` (its IMU against its ground
    truth; ``noise`` defaults to the sequence's IMU calibration, else EuRoC's ADIS16448)."""
    where = sequence.root if sequence.root is not None else sequence.name
    gt = _check_ground_truth(sequence.ground_truth, where)
    if sequence.imu is None:
        raise DataError("the least-squares offset needs IMU samples", where)
    calib = sequence.imu_calibration
    if noise is None:
        noise = calib.noise if calib is not None else EUROC_ADIS16448
    imu, R = sequence.imu, ground_truth_rotations(gt)
    return least_squares_offset(imu.t_ns, imu.gyro, imu.accel, gt.t_ns, R, gt.position,
                                gt.velocity, config, noise=noise, span=span,
                                return_std=return_std)
