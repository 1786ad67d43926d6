"""A scripted ground target: wait, straight, a turn, a stop, straight again; and a scene that
holds it.

The path (:class:`GroundPath`) starts at the world origin heading along +x: the target waits
``wait_s`` (the follower's VIO initialises meanwhile), drives ``straight_m`` metres, turns
``turn_deg`` (left for a positive angle) on an arc of ``turn_radius_m``, drives on and stops
``stop_after_m`` metres after the turn for ``stop_s`` seconds, then drives straight on until the
end. Speed changes at most ``accel`` m/s^2 (a car that starts and brakes, not one that
teleports); the heading is the path's tangent (a car faces where it drives).

:func:`ground_track` samples it as the scene's target track (``x, y, yaw`` at
:data:`~uavcal_jax.sim.follow_targets.PLAN_RATE_HZ`, :class:`~uavcal_jax.sim.scene.Targets`'
``track``); :func:`scene_with_track` builds a hall around the track and the follower's flight
(:func:`~uavcal_jax.sim.scene_build.make_scene`: obstacles off the flight region) with a car,
then puts that car on the track (target 0; a static person stands somewhere as a distractor).
Floor at world ``z = 0``.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from uavcal_jax.sim.follow_targets import PLAN_RATE_HZ
from uavcal_jax.sim.scene import CAR, PERSON, Scene, SceneConfig
from uavcal_jax.sim.scene_build import make_scene

__all__ = ["GroundPath", "ground_track", "path_point", "scene_with_track"]


@dataclasses.dataclass(frozen=True)
class GroundPath:
    """The scripted path (module docstring); lengths in metres, times in seconds.

    Attributes:
        speed: cruise speed, m/s.  accel: speed change limit, m/s^2.
        wait_s: standing still at the start.
        straight_m: first straight leg.  turn_deg: the turn (positive: left).
        turn_radius_m: the turn's radius.  stop_after_m: straight after the turn before the
        stop.  stop_s: the stop's length.
    """

    speed: float = 1.5
    accel: float = 1.0
    wait_s: float = 2.0
    straight_m: float = 9.0
    turn_deg: float = 90.0
    turn_radius_m: float = 3.0
    stop_after_m: float = 3.0
    stop_s: float = 3.0

    def __post_init__(self):
        for name in ("speed", "accel", "turn_radius_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("wait_s", "straight_m", "stop_after_m", "stop_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @property
    def stop_at_m(self) -> float:
        """Path length at which the target stops."""
        return self.straight_m + self.turn_radius_m * abs(np.radians(self.turn_deg)) \
            + self.stop_after_m


def path_point(path: GroundPath, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x``, ``y``, heading (radians) at path lengths ``s`` (metres, any shape, >= 0)."""
    s = np.asarray(s, np.float64)
    turn = np.radians(path.turn_deg)
    r = path.turn_radius_m
    arc = r * abs(turn)
    side = np.sign(turn) if turn != 0 else 1.0
    s1 = np.minimum(s, path.straight_m)
    sa = np.clip(s - path.straight_m, 0.0, arc)
    s2 = np.maximum(s - path.straight_m - arc, 0.0)
    heading = side * sa / r
    # the arc about the centre (straight_m, side r)
    ax = np.sin(heading * side) * r
    ay = side * (1.0 - np.cos(heading)) * r
    h_end = turn
    x = s1 + ax + s2 * np.cos(h_end)
    y = ay + s2 * np.sin(h_end)
    return x, y, np.where(s > path.straight_m + arc, h_end, heading)


def _speeds(path: GroundPath, duration: float, dt: float) -> np.ndarray:
    """Path length (K,) at ``k dt`` over ``duration``: wait, go, brake to the stop, stop, go."""
    K = int(np.floor(duration / dt + 1e-9)) + 1
    s, v, phase, stopped = 0.0, 0.0, "wait", 0.0
    out = np.zeros(K)
    stop_at = path.stop_at_m
    for k in range(K):
        out[k] = s
        t = k * dt
        if phase == "wait" and t >= path.wait_s:
            phase = "go"
        if phase == "go":
            room = stop_at - s
            # brake so that the stop lands on stop_at (v^2 = 2 a room)
            want = min(path.speed, np.sqrt(2.0 * path.accel * max(room, 0.0)))
            v = min(v + path.accel * dt, want)
            if room <= 1e-3 or (v <= 1e-6 and room < 0.05):
                phase, v = "stop", 0.0
        elif phase == "stop":
            stopped += dt
            if stopped >= path.stop_s:
                phase = "again"
        elif phase == "again":
            v = min(v + path.accel * dt, path.speed)
        s += v * dt
    return out


def ground_track(path: GroundPath, duration: float, origin=(0.0, 0.0), heading: float = 0.0,
                 rate_hz: float = PLAN_RATE_HZ) -> np.ndarray:
    """(K, 3) float64 ``x, y, yaw`` (world metres; radians, unwrapped) of the box centre at
    scene times ``k / rate_hz`` over ``[0, duration]``, the path started at ``origin`` (2,)
    heading ``heading`` (radians)."""
    s = _speeds(path, float(duration), 1.0 / rate_hz)
    x, y, h = path_point(path, s)
    c, sn = np.cos(heading), np.sin(heading)
    return np.stack([origin[0] + c * x - sn * y, origin[1] + sn * x + c * y, h + heading], -1)


def scene_with_track(track: np.ndarray, flight_lo, flight_hi, seed: int = 0,
                     config: SceneConfig | None = None, tries: int = 20) -> Scene:
    """A hall around ``track`` (K, 3) (:func:`ground_track`) and the follower's flight region
    ``[flight_lo, flight_hi]`` (3,) each, world metres, floor at z = 0, with the car on the
    track as target 0 (a static person, target 1, stands off the flight region).

    The region (the track's and the flight's bounds, from the floor up) is kept clear of
    obstacles and of the person (``make_scene`` without path points keeps its bounds box
    clear). Seeds ``seed, seed + 1, ...`` are tried until both targets are placed.

    Raises:
        ValueError: no seed among ``tries`` placed both targets (a hall too small).
    """
    cfg = config or SceneConfig()
    cfg = dataclasses.replace(cfg, n_targets=2, target_classes=(CAR, PERSON), moving_fraction=0.0)
    track = np.asarray(track, np.float64)
    lo = np.minimum(np.asarray(flight_lo, np.float64), [*track[:, :2].min(0), 0.0])
    hi = np.maximum(np.asarray(flight_hi, np.float64), [*track[:, :2].max(0), 0.0])
    lo[2] = cfg.margin_below  # the floor (lo - margin_below) at z = 0
    hi[2] = max(hi[2], lo[2])
    for k in range(tries):
        scn = make_scene(lo, hi, seed + k, cfg)
        ids = np.asarray(scn.targets.class_id)
        if ids.tolist() == [CAR, PERSON]:
            break
    else:
        raise ValueError(f"no scene with a car and a person in {tries} seeds from {seed}")
    tg = scn.targets
    K = track.shape[0]
    full = np.zeros((2, K, 3), np.float32)
    full[0] = track
    targets = dataclasses.replace(
        tg, tracked=jnp.asarray([True, False]), track=jnp.asarray(full),
        track_t0=jnp.zeros(2, jnp.float32),
        track_dt=jnp.full(2, 1.0 / PLAN_RATE_HZ, jnp.float32))
    return dataclasses.replace(scn, targets=targets)
