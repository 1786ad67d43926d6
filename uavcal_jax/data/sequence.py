"""In-memory recording: calibration, lazily loaded frames, IMU samples and ground truth.

Every reader (EuRoC ASL, ROS bags, the simulator's output) produces a :class:`Sequence`.
Times are float64 seconds (``t``) next to the exact int64 nanoseconds (``t_ns``) they came
from. Quaternions are (w, x, y, z). The body frame is the IMU frame; the world frame is z up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uavcal_jax.errors import DataError
from uavcal_jax.imu.noise import ImuNoise


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole camera with radial-tangential distortion, as in EuRoC's ``sensor.yaml``.

    Attributes:
        intrinsics: (4,) ``fu, fv, cu, cv`` in pixels.
        distortion: (4,) ``k1, k2, p1, p2`` (OpenCV order).
        resolution: ``(width, height)`` in pixels.
        rate_hz: nominal frame rate.
        T_BS: (4, 4) sensor-to-body transform (maps points in the camera frame to the body frame).
    """

    intrinsics: np.ndarray
    distortion: np.ndarray
    resolution: tuple[int, int]
    rate_hz: float
    T_BS: np.ndarray
    camera_model: str = "pinhole"
    distortion_model: str = "radial-tangential"

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        fu, fv, cu, cv = self.intrinsics
        return np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ImuCalibration:
    """IMU rate, extrinsics and continuous-time noise model (Kalibr / EuRoC ``sensor.yaml``).

    Attributes:
        rate_hz: nominal sample rate.
        T_BS: (4, 4) sensor-to-body transform (identity when the body frame is the IMU frame).
        noise: the noise densities and random walks, see :class:`~uavcal_jax.imu.noise.ImuNoise`.
    """

    rate_hz: float
    T_BS: np.ndarray
    noise: ImuNoise


class _Timestamped:
    """Samples stamped by ``t_ns`` (N,) int64 nanoseconds."""

    t_ns: np.ndarray

    @property
    def t(self) -> np.ndarray:
        """(N,) float64 seconds."""
        return self.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class ImuData(_Timestamped):
    """IMU samples in the IMU (body) frame.

    Attributes:
        t_ns: (N,) int64 nanoseconds, strictly increasing.
        gyro: (N, 3) angular rate, rad/s.
        accel: (N, 3) specific force, m/s^2.
    """

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray


@dataclass(frozen=True)
class GroundTruth(_Timestamped):
    """Ground-truth body (IMU) states in the world frame.

    Attributes:
        t_ns: (N,) int64 nanoseconds.
        position: (N, 3) metres, world frame.
        quaternion: (N, 4) body-to-world rotation, (w, x, y, z).
        velocity: (N, 3) m/s in the world frame, or ``None`` (TUM files carry none).
        bias_gyro: (N, 3) rad/s, or ``None``.
        bias_accel: (N, 3) m/s^2, or ``None``.
    """

    t_ns: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray | None = None
    bias_gyro: np.ndarray | None = None
    bias_accel: np.ndarray | None = None


@dataclass(frozen=True)
class FrameStream:
    """Timestamped images of one camera, loaded from disk only when asked for.

    Attributes:
        name: sensor folder name, e.g. ``"cam0"``.
        t_ns: (N,) int64 nanoseconds.
        paths: N image paths (empty when frames live in memory, see ``loader``).
        calibration: the camera's calibration.
        loader: ``loader(i, color) -> image``; readers set it. ``color`` is ``"gray"``
            (H, W) uint8 or ``"rgb"`` (H, W, 3) uint8.
    """

    name: str
    t_ns: np.ndarray
    paths: tuple[Path, ...]
    calibration: CameraCalibration
    loader: Callable[[int, str], np.ndarray] = field(repr=False, compare=False)

    @property
    def t(self) -> np.ndarray:
        return self.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def load(self, index: int, color: str = "gray") -> np.ndarray:
        """Image ``index`` as uint8, (H, W) for ``"gray"`` or (H, W, 3) RGB for ``"rgb"``."""
        if color not in ("gray", "rgb"):
            raise ValueError(f"color must be 'gray' or 'rgb', got {color!r}")
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: frame {index} out of range [0, {len(self)})")
        return self.loader(index, color)


@dataclass(frozen=True)
class Sequence:
    """One recording: cameras, IMU, ground truth and calibration.

    Attributes:
        name: a human-readable name (folder name for EuRoC).
        root: where it was read from, or ``None``.
        cameras: frame streams by sensor name (``"cam0"``, ``"cam1"``); may be empty.
        imu: IMU samples, or ``None``.
        imu_calibration: IMU noise model and extrinsics, or ``None``.
        ground_truth: ground-truth states, or ``None``.
        depth: depth streams by name (``"depth0"``: uint16 PNG, millimetres, z-depth in the
            camera frame of the same-numbered camera), from the simulator.
        targets: per-frame target labels from the simulator (see ``uavcal_jax.data.targets``),
            or ``None``.
    """

    name: str
    root: Path | None
    cameras: dict[str, FrameStream]
    imu: ImuData | None
    imu_calibration: ImuCalibration | None
    ground_truth: GroundTruth | None
    depth: dict[str, FrameStream] = field(default_factory=dict)
    targets: object | None = None

    def camera(self, name: str = "cam0") -> FrameStream:
        try:
            return self.cameras[name]
        except KeyError:
            where = self.root if self.root is not None else self.name
            raise DataError(
                f"no camera {name!r} in this sequence (have {sorted(self.cameras)})", where
            ) from None
