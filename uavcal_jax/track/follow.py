"""Follow set-points: stand off a target at a fixed horizontal distance and height, facing it.

Pure JAX (jit/vmap-able). World frame z up; yaw is the heading of the body's x axis about
world z, radians, wrapped to ``[-pi, pi)``. The law answers two complaints about PX4 and
ArduPilot follow modes, set-points that step and yaw that oscillates:

- The desired position is on the horizontal line from the target to the drone's *current*
  position, ``distance`` from the target, at height ``target_z + height``. (Where the drone is
  right above the target the line has no direction; the previous yaw set-point's backward
  direction is used.)
- The position set-point moves from the previous one towards the desired position by at most
  ``max_speed * dt``: no steps, whatever the target does.
- The desired yaw faces the target from the drone's *actual* position (not from the previous
  set-point), and is only updated when the target is more than ``min_yaw_distance``
  horizontally away (near it the bearing is noise). The yaw set-point turns towards it the
  short way round, at most ``max_yaw_rate * dt``, and is wrapped.

A target without an estimate holds the set-points; a lost target is followed at its last
prediction, which :func:`uavcal_jax.track.filter.filter_step` holds in its output.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "FollowConfig",
    "Setpoint",
    "desired_position",
    "follow_step",
    "wrap_angle",
]


@dataclasses.dataclass(frozen=True)
class FollowConfig:
    """Settings of the follow law (hashable; every default documented here).

    Attributes:
        distance: horizontal stand-off from the target, metres.
        height: height above the target's centre, metres. The defaults (6 m, 3 m: 26.6
            degrees below the horizon, the centre of a rig pitched 30 degrees down) keep a
            4.2 m car whole in a EuRoC-lens view; at 4 m and 2 m its near end leaves the
            image's bottom edge, and a detector's boxes of a cut car place it 0.25 m too near
            (the closed loop's distance error was 0.63 m, against 0.26 m at 6 m and 3 m).
            PX4's follow-target mode defaults to 8 m and 8 m.
        max_speed: the position set-point moves at most this fast, m/s.
        max_yaw_rate: the yaw set-point turns at most this fast, rad/s.
        min_yaw_distance: below this horizontal drone-to-target distance (metres) the yaw
            set-point is held.
    """

    distance: float = 6.0
    height: float = 3.0
    max_speed: float = 2.0
    max_yaw_rate: float = 1.0
    min_yaw_distance: float = 0.5

    def __post_init__(self):
        if self.distance < 0.0:
            raise ValueError(f"distance must be >= 0, got {self.distance}")
        if self.max_speed <= 0.0 or self.max_yaw_rate <= 0.0:
            raise ValueError("max_speed and max_yaw_rate must be > 0")
        if self.min_yaw_distance < 0.0:
            raise ValueError(f"min_yaw_distance must be >= 0, got {self.min_yaw_distance}")


class Setpoint(NamedTuple):
    """A position set-point (3,) (world, metres) and a yaw set-point () (radians)."""

    position: jax.Array
    yaw: jax.Array


def wrap_angle(angle):
    """Angles (radians) wrapped to ``[-pi, pi)``."""
    return jnp.mod(angle + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def desired_position(target, drone, fallback_yaw, config: FollowConfig = FollowConfig()):
    """(3,) the stand-off point: on the horizontal line from ``target`` (3,) to ``drone`` (3,),
    ``distance`` from the target, at ``target_z + height``. Where the drone is (nearly) above
    the target, the direction is the one behind a drone of yaw ``fallback_yaw`` facing it."""
    target, drone = jnp.asarray(target), jnp.asarray(drone)
    away = drone[:2] - target[:2]
    norm = jnp.linalg.norm(away)
    fallback = -jnp.stack([jnp.cos(fallback_yaw), jnp.sin(fallback_yaw)]).astype(away.dtype)
    tiny = 1e-6
    direction = jnp.where(norm > tiny, away / jnp.where(norm > tiny, norm, 1.0), fallback)
    xy = target[:2] + config.distance * direction
    return jnp.concatenate([xy, target[2:3] + config.height])


@functools.partial(jax.jit, static_argnames="config")
def follow_step(previous: Setpoint, target, target_known, drone, dt,
                config: FollowConfig = FollowConfig()) -> Setpoint:
    """The next set-point.

    Args:
        previous: the last :class:`Setpoint` (start from the drone's own pose).
        target: (3,) the target's (filtered) world position, metres.
        target_known: () bool, ``target`` is an estimate (else the set-points are held).
        drone: (3,) the drone's actual world position, metres.
        dt: () seconds since the previous set-point.
        config: :class:`FollowConfig`.

    Returns:
        :class:`Setpoint`.
    """
    target, drone = jnp.asarray(target), jnp.asarray(drone)
    prev_p, prev_yaw = jnp.asarray(previous.position), jnp.asarray(previous.yaw)
    known = jnp.asarray(target_known) & jnp.all(jnp.isfinite(target))
    target = jnp.where(known, target, drone)  # keeps the arithmetic finite; result unused

    goal = desired_position(target, drone, prev_yaw, config)
    step = goal - prev_p
    length = jnp.linalg.norm(step)
    limit = config.max_speed * dt
    scale = jnp.where(length > limit, limit / jnp.where(length > 0, length, 1.0), 1.0)
    position = jnp.where(known, prev_p + scale * step, prev_p)

    to_target = target[:2] - drone[:2]
    far = jnp.linalg.norm(to_target) > config.min_yaw_distance
    bearing = jnp.arctan2(to_target[1], to_target[0])
    turn = wrap_angle(jnp.where(known & far, bearing, prev_yaw) - prev_yaw)
    max_turn = config.max_yaw_rate * dt
    yaw = wrap_angle(prev_yaw + jnp.clip(turn, -max_turn, max_turn))
    return Setpoint(position, yaw)
