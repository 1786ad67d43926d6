"""Training with random IMU mountings (issue 20, item 3): ``train.mounting="random"``.

Recordings from other drones hold the IMU in other orientations (gravity along +x in EuRoC's
IMU frame, along +z in many others). A calibrator trained on one mounting learns that
mounting: its accelerometer estimate leans on where gravity sits in the IMU frame. Under
``"random"`` every training window is read through its own IMU mounting: a rotation ``R``
drawn uniformly on SO(3) (:func:`random_mountings`) turns the IMU frame, so that a vector
``v`` of the recorded IMU frame reads ``R^T v`` in the new one (:func:`remount`):

- the clean IMU samples ``imu (B, T, C)`` and the full-rate gyro of the motion inputs
  ``gyro_seq (B, T, S, 3)``: ``v R`` (row vectors);
- the body rotations the camera sees over each interval, ``rot_cam (B, T, 3, 3)``:
  ``R^T rot_cam R``;
- the sensor's own bias of the ``total`` label, ``bias (B, C)``, and the tilt head's label
  ``up (B, T, 3)``: ``v R``.

The frames do not change (the camera stays on the airframe; only the IMU turns). The offset
is drawn afterwards, in the turned frame, as the protocol draws it. Standardisation then
cannot assume the recorded mounting either: :func:`isotropic_statistics` gives every axis of a
sensor the same mean (0) and spread (the RMS of that sensor's samples per axis), the statistics
of the training IMU averaged over all mountings. Validation windows keep their recorded
mounting: they measure what the invariance costs on it.

The paper protocol draws offsets around the IMU's per-channel mean, gravity included; over all
mountings that mean is 0, so the two do not combine (:class:`~uavcal_jax.calib.config.CalibConfig`
refuses them).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.calib.inject import ImuStats
from uavcal_jax.geometry import so3

__all__ = ["isotropic_statistics", "random_mountings", "remount"]


def random_mountings(key: jax.Array, n: int) -> jax.Array:
    """``(n, 3, 3)`` float32 rotations drawn uniformly on SO(3) (a normalised 4-D Gaussian is
    a uniform unit quaternion)."""
    return so3.from_quaternion(jax.random.normal(key, (n, 4), jnp.float32)).astype(jnp.float32)


def _turn_triplets(values: jax.Array, R: jax.Array) -> jax.Array:
    """``values (B, ..., C)`` (C = 3 or 6: whole sensor triplets) with each triplet ``v`` read
    in the frame turned by ``R (B, 3, 3)``: ``R^T v``, i.e. ``v R`` for row vectors."""
    lead = values.shape[1:-1]
    Rb = R.reshape(R.shape[:1] + (1,) * len(lead) + (3, 3))
    parts = [jnp.einsum("...i,...ij->...j", values[..., c:c + 3], Rb)
             for c in range(0, values.shape[-1], 3)]
    return jnp.concatenate(parts, axis=-1)


def remount(batch: dict, R: jax.Array) -> dict:
    """``batch`` (a training batch of :mod:`uavcal_jax.calib.train`) read through the IMU
    mountings ``R (B, 3, 3)`` (module docstring): ``imu``, ``bias``, ``gyro_seq`` and
    ``rot_cam`` (and the tilt label ``up``) turned where present, everything else unchanged."""
    R = jnp.asarray(R, jnp.float32)
    out = dict(batch)
    for name in ("imu", "bias", "gyro_seq", "up"):
        if name in batch:
            out[name] = _turn_triplets(jnp.asarray(batch[name], jnp.float32), R)
    if "rot_cam" in batch:
        Rb = R[:, None]
        out["rot_cam"] = jnp.swapaxes(Rb, -1, -2) @ jnp.asarray(batch["rot_cam"],
                                                                jnp.float32) @ Rb
    return out


def isotropic_statistics(stats: ImuStats) -> ImuStats:
    """The per-channel statistics ``stats`` (``(C,)``, C = 3 or 6) of the IMU averaged over
    uniformly random mountings: mean 0 and, on every axis of a sensor, the RMS per axis of
    that sensor's samples, ``sqrt(mean over its axes of std^2 + mean^2)``."""
    mean = jnp.asarray(stats.mean, jnp.float32)
    std = jnp.asarray(stats.std, jnp.float32)
    power = (jnp.square(std) + jnp.square(mean)).reshape(-1, 3)
    rms = jnp.sqrt(jnp.mean(power, axis=-1, keepdims=True))
    return ImuStats(jnp.zeros_like(mean), jnp.broadcast_to(rms, power.shape).reshape(-1))
