"""Additive IMU offsets: the constant (3 gyro + 3 accel) error the calibrator predicts.

An IMU with offset ``o`` reads ``gyro + o[:3]`` and ``accel + o[3:]``. :func:`add_offset`
injects an offset into clean samples (to make training data, or to corrupt a recording);
:func:`remove_offset` corrects samples with an estimate. ``preintegrate(..., offset=o)``
removes it inside the preintegration, differentiably.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["add_offset", "remove_offset", "split_offset"]


def split_offset(offset) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(gyro (..., 3), accel (..., 3))`` parts of a (..., 6) offset."""
    offset = jnp.asarray(offset)
    if offset.shape[-1] != 6:
        raise ValueError(f"an IMU offset is (..., 6) (gyro xyz, accel xyz), got {offset.shape}")
    return offset[..., :3], offset[..., 3:]


def add_offset(gyro, accel, offset):
    """Samples ``(gyro, accel)`` (..., N, 3) as read by an IMU with ``offset`` (..., 6)."""
    og, oa = split_offset(offset)
    return jnp.asarray(gyro) + og[..., None, :], jnp.asarray(accel) + oa[..., None, :]


def remove_offset(gyro, accel, offset):
    """Samples corrected for ``offset`` (..., 6): the inverse of :func:`add_offset`."""
    og, oa = split_offset(offset)
    return jnp.asarray(gyro) - og[..., None, :], jnp.asarray(accel) - oa[..., None, :]
