"""EuRoC's VI-sensor rig: the two lenses, their extrinsics, the IMU's rate and bias scale, and how
the rig sits on the MAV.

The camera numbers are those of ``mav0/cam0/sensor.yaml`` and ``mav0/cam1/sensor.yaml``,
identical in every EuRoC MAV sequence: pinhole intrinsics ``fu, fv, cu, cv`` (pixels),
radial-tangential distortion ``k1, k2, p1, p2``, 752x480 pixels at 20 Hz, and ``T_BS`` (4, 4),
the camera-to-body transform (the body frame is the IMU frame); its ADIS16448 IMU samples at
200 Hz. :func:`euroc_imu_mounting` is
the IMU's orientation on the MAV, measured from the ground truth. The simulator renders this rig;
tests compare against it.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.data.sequence import CameraCalibration
from uavcal_jax.geometry.camera import PinholeRadtan, from_calibration

__all__ = [
    "EUROC_CAM0_DISTORTION",
    "EUROC_CAM0_INTRINSICS",
    "EUROC_CAM0_T_BS",
    "EUROC_CAM1_DISTORTION",
    "EUROC_CAM1_INTRINSICS",
    "EUROC_CAM1_T_BS",
    "EUROC_BIAS_SCALE",
    "EUROC_CAMERA_PITCH_DEG",
    "EUROC_IMU_RATE_HZ",
    "EUROC_RATE_HZ",
    "EUROC_RESOLUTION",
    "euroc_calibration",
    "euroc_camera",
    "euroc_imu_mounting",
]

EUROC_RESOLUTION: tuple[int, int] = (752, 480)  # (width, height)
EUROC_RATE_HZ: float = 20.0  # the cameras' frame rate
#: The IMU's (and the ground truth's) sample rate, Hz.
EUROC_IMU_RATE_HZ: float = 200.0
#: The size of EuRoC's ground-truth IMU biases in norm: (gyro rad/s, accel m/s^2). The
#: calibrator's physical offset range and the scale of offset errors.
EUROC_BIAS_SCALE: tuple[float, float] = (0.08, 0.16)
EUROC_CAM0_INTRINSICS = np.array([458.654, 457.296, 367.215, 248.375])  # fu, fv, cu, cv
EUROC_CAM0_DISTORTION = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
EUROC_CAM0_T_BS = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
EUROC_CAM1_INTRINSICS = np.array([457.587, 456.134, 379.999, 255.238])
EUROC_CAM1_DISTORTION = np.array([-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05])
EUROC_CAM1_T_BS = np.array(
    [
        [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
        [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
        [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

#: EuRoC's cameras look this far below the horizon in level flight (the median over EuRoC's
#: ground truth of the IMU z axis' elevation: -20.2 deg V1_01, -19.3 MH_01, -19.2 V2_01).
EUROC_CAMERA_PITCH_DEG = 20.0


_CAMERAS = {
    0: (EUROC_CAM0_INTRINSICS, EUROC_CAM0_DISTORTION, EUROC_CAM0_T_BS),
    1: (EUROC_CAM1_INTRINSICS, EUROC_CAM1_DISTORTION, EUROC_CAM1_T_BS),
}


def euroc_calibration(index: int = 0) -> CameraCalibration:
    """EuRoC's cam0 (``index=0``) or cam1 (``index=1``) as a :class:`CameraCalibration`
    (fresh numpy float64 copies, 752x480, 20 Hz)."""
    intr, dist, T_BS = _CAMERAS[index]
    return CameraCalibration(
        intrinsics=intr.copy(),
        distortion=dist.copy(),
        resolution=EUROC_RESOLUTION,
        rate_hz=EUROC_RATE_HZ,
        T_BS=T_BS.copy(),
    )


def euroc_camera(index: int = 0, dtype=None) -> PinholeRadtan:
    """EuRoC's cam0/cam1 lens as a JAX camera model (parameters of ``dtype``, see
    :meth:`PinholeRadtan.create`)."""
    return from_calibration(euroc_calibration(index), dtype)


def euroc_imu_mounting(pitch_deg: float = EUROC_CAMERA_PITCH_DEG) -> np.ndarray:
    """(3, 3) ``R_QB``: EuRoC's IMU (body) axes in a quadrotor frame (x forward, y left, z up).

    EuRoC's VI-sensor has its IMU x axis up and z axis (where the cameras look) forward,
    pitched ``pitch_deg`` below the horizon; y points right.
    """
    th = np.radians(pitch_deg)
    s, c = np.sin(th), np.cos(th)
    return np.array([[s, 0.0, c], [0.0, -1.0, 0.0], [c, 0.0, -s]])
