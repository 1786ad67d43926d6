"""Model inputs from window batches: the one place that knows both layouts.

:meth:`uavcal_jax.data.windows.WindowSet.batch` gives ``frames (B, T, H, W[, 3])`` uint8
(channel-last, as OpenCV decodes), ``gyro``/``accel (B, T, 3)`` and ``mask (B, T)``. The
model reads ``frames (B, T, H, W)`` gray or ``(B, T, 3, H, W)`` RGB (channel-first, the
paper's ``n x 3 x h x w``), ``imu (B, T, C)`` float32 and ``mask (B, T)`` bool.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.calib.config import ModelConfig

__all__ = ["IMU_SENSORS", "frames_to_model", "model_batch", "model_imu"]

IMU_SENSORS = ("gyro", "accel")


def frames_to_model(frames: np.ndarray, rgb: bool) -> np.ndarray:
    """Frames ``(..., H, W)`` (gray) or ``(..., H, W, 3)`` (RGB, channel-last) in the model's
    layout: unchanged, or ``(..., 3, H, W)``."""
    frames = np.asarray(frames)
    if not rgb:
        return frames
    if frames.shape[-1] != 3:
        raise ValueError(f"an RGB model needs frames (..., H, W, 3), got {frames.shape}; "
                         "cut windows with color='rgb'")
    return np.moveaxis(frames, -1, -3)


def model_imu(window_batch: dict, config: ModelConfig, sensor: str = "gyro") -> np.ndarray:
    """The model's ``imu (B, T, C)`` float32 from a :meth:`WindowSet.batch` /
    :meth:`WindowSet.samples` dict: gyro then accel, or with ``config.imu_channels == 3``
    the one ``sensor`` (``"gyro"`` or ``"accel"``)."""
    if config.imu_channels == 6:
        imu = np.concatenate([window_batch["gyro"], window_batch["accel"]], axis=-1)
    elif sensor in IMU_SENSORS:
        imu = window_batch[sensor]
    else:
        raise ValueError(f"sensor must be one of {IMU_SENSORS}, got {sensor!r}")
    return np.asarray(imu, np.float32)


def model_batch(window_batch: dict, config: ModelConfig, sensor: str = "gyro") -> dict:
    """``{"frames", "imu", "mask"}`` model inputs from a :meth:`WindowSet.batch` dict
    (:func:`model_imu` for the IMU). An ``"offset"`` entry, when present, is passed through
    as float32 ``(B, C)``."""
    out = {"imu": model_imu(window_batch, config, sensor),
           "mask": np.asarray(window_batch["mask"], bool)}
    if config.use_video:
        out["frames"] = frames_to_model(window_batch["frames"], config.rgb)
    if "offset" in window_batch:
        out["offset"] = np.asarray(window_batch["offset"], np.float32)
    return out
