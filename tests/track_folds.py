"""The target stage's per-frame steps folded over whole sequences: the references the filter,
follow and association tests check properties over time against (the library runs the steps
one frame at a time, :class:`uavcal_jax.pipeline.tracker.TargetTracker`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from uavcal_jax.track.associate import AssociateConfig, Associator
from uavcal_jax.track.filter import FilterConfig, FilterOutput, filter_start, filter_step
from uavcal_jax.track.follow import FollowConfig, Setpoint, follow_step

FILTER, FOLLOW, ASSOCIATE = FilterConfig(), FollowConfig(), AssociateConfig()


@functools.partial(jax.jit, static_argnames="config")
def run_filter(times, measurements, covariances, valid,
               config: FilterConfig = FILTER) -> FilterOutput:
    """:func:`~uavcal_jax.track.filter.filter_step` scanned over ``T`` frames: times (T,)
    seconds, measurements (T, 3) metres, covariances (T, 3, 3) m^2, valid (T,) bool; one
    :class:`FilterOutput` row per frame."""
    measurements = jnp.asarray(measurements)
    dtype = measurements.dtype
    times = jnp.asarray(times, dtype)

    def step(carry, frame):
        return filter_step(carry, *frame, config=config)

    frames = (times, measurements, jnp.asarray(covariances, dtype), jnp.asarray(valid, bool))
    return jax.lax.scan(step, filter_start(times[0], dtype), frames)[1]


def follow_setpoints(times, targets, target_known, drone_positions, start: Setpoint,
                     config: FollowConfig = FOLLOW) -> Setpoint:
    """:func:`~uavcal_jax.track.follow.follow_step` scanned over ``T`` frames (times (T,)
    seconds, the first frame's ``dt`` 0; targets and drone positions (T, 3); target_known
    (T,) bool) from ``start``: position (T, 3), yaw (T,)."""
    times = jnp.asarray(times)
    dts = jnp.diff(times, prepend=times[:1])

    def step(prev, frame):
        dt, target, known, drone = frame
        nxt = follow_step(prev, target, known, drone, dt, config)
        return nxt, nxt

    start = Setpoint(jnp.asarray(start.position, times.dtype), jnp.asarray(start.yaw, times.dtype))
    frames = (dts, jnp.asarray(targets, times.dtype), jnp.asarray(target_known, bool),
              jnp.asarray(drone_positions, times.dtype))
    return jax.lax.scan(step, start, frames)[1]


def assign_track_ids(boxes, class_ids, config: AssociateConfig = ASSOCIATE, same=None):
    """Per frame, (N_k,) track ids of the boxes (N_k, 4) of classes (N_k,):
    :class:`~uavcal_jax.track.associate.Associator` stepped over the frames."""
    associator = Associator(config)
    return [associator.step(b, c, same) for b, c in zip(boxes, class_ids, strict=True)]
