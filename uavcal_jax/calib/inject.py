"""Offset injection for training and validation (Avola et al. 2023, section 3.4, eq. 12).

Windows hold clean IMU samples; a constant offset ``o (C,)`` per window is drawn and added to
every real sample of it (:func:`inject`, via :func:`uavcal_jax.imu.offset.add_offset` for
6-channel IMUs), and the model learns to predict ``o``. Protocols
(:class:`~uavcal_jax.calib.config.InjectionConfig`), per channel ``c``:

- ``"paper"``: ``o_c ~ N(mu_c, n_m sigma_c^2)``, ``mu``/``sigma`` the training set's
  per-channel IMU mean and standard deviation (:func:`imu_statistics`), ``n_m = 2``. The
  accelerometer's mean holds gravity, so accel offsets are several m/s^2.
- ``"symmetric"``: ``o_c ~ U(-n_m sigma_c, n_m sigma_c)``, the interval the text also
  describes, centred on zero.
- ``"physical"``: ``o_c ~ U(-r_c, r_c)`` with ``r`` the configured gyro (rad/s) / accel
  (m/s^2) range: the size of real IMU biases, independent of the data.

Training draws a new offset for every sample (:func:`training_offsets`); a validation set of
one trial shares one offset (:func:`validation_offsets`). All draws take explicit keys and
are vmapped over the batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.calib.config import InjectionConfig
from uavcal_jax.data.windows import WindowSet
from uavcal_jax.imu.offset import add_offset

__all__ = [
    "ImuStats",
    "imu_statistics",
    "inject",
    "offset_moments",
    "physical_bounds",
    "sample_offset",
    "training_offsets",
    "validation_offsets",
    "window_samples",
]


class ImuStats(NamedTuple):
    """Per-channel IMU statistics of a training set: ``mean (C,)``, ``std (C,)`` (gyro in
    rad/s, accel in m/s^2)."""

    mean: jax.Array
    std: jax.Array


def window_samples(ws: WindowSet, indices=None) -> np.ndarray:
    """Every IMU sample inside any window of ``ws`` (or only of the windows ``indices``),
    ``(N, 6)`` (gyro rad/s, accel m/s^2), each sample once however many windows hold it."""
    covered = np.zeros(ws.imu_t_ns.shape[0], bool)
    ranges = ws.imu_range if indices is None else ws.imu_range[np.asarray(indices)]
    for lo, hi in ranges:
        covered[lo:hi] = True
    return np.concatenate([ws.gyro[covered], ws.accel[covered]], axis=1)


def imu_statistics(source, mask=None) -> ImuStats:
    """Per-channel mean and (population) standard deviation of training IMU samples.

    ``source``: a :class:`WindowSet` or a sequence of them (every IMU sample inside any
    window, 6 channels), or an array ``(..., C)`` of samples with an optional boolean
    ``mask`` of its leading shape (``False`` rows, e.g. padded frames, are left out).
    Statistics are accumulated in float64 and returned as float32.
    """
    if isinstance(source, WindowSet):
        samples = window_samples(source)
    elif isinstance(source, Sequence) and source and all(isinstance(s, WindowSet)
                                                        for s in source):
        samples = np.concatenate([window_samples(s) for s in source])
    else:
        arr = np.asarray(source, np.float64)
        samples = arr.reshape(-1, arr.shape[-1])
        if mask is not None:
            samples = samples[np.asarray(mask, bool).reshape(-1)]
    if samples.shape[0] == 0:
        raise ValueError("no IMU samples to compute statistics from")
    return ImuStats(jnp.asarray(samples.mean(axis=0), jnp.float32),
                    jnp.asarray(samples.std(axis=0), jnp.float32))


def physical_bounds(config: InjectionConfig, channels: int) -> jax.Array:
    """Per-channel half-ranges ``(C,)`` of the physical protocol."""
    g, a = config.gyro_range, config.accel_range
    if channels == 6:
        return jnp.asarray([g, g, g, a, a, a], jnp.float32)
    if channels == 3:
        return jnp.full((3,), g if config.single_sensor == "gyro" else a, jnp.float32)
    raise ValueError(f"an IMU has 3 or 6 channels, got {channels}")


def _half_width(config: InjectionConfig, std: jax.Array) -> jax.Array:
    """Per-channel half-range of the uniform protocols ``(C,)``."""
    if config.protocol == "symmetric":
        return jnp.float32(config.noise_multiplier) * std
    return physical_bounds(config, std.shape[0])


def sample_offset(key: jax.Array, config: InjectionConfig, stats: ImuStats) -> jax.Array:
    """One offset ``(C,)`` drawn by ``config.protocol`` (``C`` from ``stats``)."""
    mean = jnp.asarray(stats.mean, jnp.float32)
    std = jnp.asarray(stats.std, jnp.float32)
    if config.protocol == "paper":
        nm = jnp.float32(config.noise_multiplier)
        return mean + jnp.sqrt(nm) * std * jax.random.normal(key, mean.shape, jnp.float32)
    return jax.random.uniform(key, mean.shape, jnp.float32, -1.0, 1.0) * _half_width(config,
                                                                                   std)


def offset_moments(config: InjectionConfig, stats: ImuStats) -> tuple[jax.Array, jax.Array]:
    """Mean and standard deviation ``(C,)`` of the offsets :func:`sample_offset` draws: the
    units a standardised model predicts in (``paper``: ``mu``, ``sqrt(n_m) sigma``;
    ``symmetric``: 0, ``n_m sigma / sqrt(3)``; ``physical``: 0, ``r / sqrt(3)``)."""
    mean = jnp.asarray(stats.mean, jnp.float32)
    std = jnp.asarray(stats.std, jnp.float32)
    if config.protocol == "paper":
        return mean, jnp.sqrt(jnp.float32(config.noise_multiplier)) * std
    return jnp.zeros_like(mean), _half_width(config, std) / jnp.sqrt(jnp.float32(3.0))


def training_offsets(key: jax.Array, config: InjectionConfig, stats: ImuStats,
                     batch: int) -> jax.Array:
    """A new offset for each of ``batch`` samples, ``(batch, C)`` (one key per sample)."""
    keys = jax.random.split(key, batch)
    return jax.vmap(lambda k: sample_offset(k, config, stats))(keys)


def validation_offsets(key: jax.Array, config: InjectionConfig, stats: ImuStats,
                       n: int) -> jax.Array:
    """One offset for a whole validation set of ``n`` windows, ``(n, C)``, every row equal."""
    o = sample_offset(key, config, stats)
    return jnp.broadcast_to(o, (n,) + o.shape)


def _inject_one(imu: jax.Array, offset: jax.Array, mask: jax.Array) -> jax.Array:
    """One window: ``imu (T, C)`` read through ``offset (C,)``; padded rows stay zero."""
    if imu.shape[-1] == 6:
        g, a = add_offset(imu[:, :3], imu[:, 3:], offset)
        out = jnp.concatenate([g, a], axis=-1)
    else:
        out = imu + offset  # one sensor: the offset adds to its 3 axes alike
    return jnp.where(mask[:, None], out, imu)


def inject(imu: jax.Array, offsets: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """IMU windows ``(B, T, C)`` with ``offsets (B, C)`` added to every real sample
    (``mask (B, T)``, default all), vmapped over the batch."""
    imu = jnp.asarray(imu, jnp.float32)
    offsets = jnp.asarray(offsets, jnp.float32)
    mask = jnp.ones(imu.shape[:2], bool) if mask is None else jnp.asarray(mask, bool)
    return jax.vmap(_inject_one)(imu, offsets, mask)
