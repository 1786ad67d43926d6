"""Targets to follow: ground tracks that stay where a flight's left camera looks.

The scene's ordinary targets stand still or circle on fixed ellipses, so a flight sees them only
if its camera happens to look there. A *follow target* is planned from the flight instead:

1. **Aim.** At every planning step (:data:`PLAN_RATE_HZ`) the left camera's rays through the
   image's vertical centre line, from 40 % of the way up to the top edge to 80 % of the way
   down to the bottom edge, are cut with the floor; the hit whose distance from the camera is
   nearest the class's preferred viewing distance (:data:`PREFERRED_DISTANCE_M`: a car about a
   quarter of the image wide, a person about a third of it tall), with a penalty for leaving
   the image centre (:data:`CENTRE_WEIGHT`), is the aim point. When no ray reaches the
   floor (the camera looks up) the aim holds its last value. The aim track is smoothed
   (:data:`AIM_SMOOTHING_S`) so that the target does not copy the drone's jitter.
2. **Wander.** The target's goal is the aim plus a slow wander (two sinusoids per axis, periods
   5-14 s) of a radius that grows with the camera's ground footprint (:data:`WANDER`), plus a
   lateral slot when several targets share the view (:data:`SLOT_SPREAD`).
3. **Drive.** A unicycle (position, heading, forward speed only: it cannot move sideways)
   steers to the goal with feed-forward of the aim's velocity, a turn-rate and acceleration
   limit per class, and a speed limit that is the class's (a person walks, a car drives)
   or, when the drone is faster, enough to keep up with the camera; a car backs up rather
   than turning round for a goal behind it at low speed. It stops now and then for
   0.8-2.5 s (a person turns in place while stopped) when the camera lingers, and resumes when
   the goal moves away. Targets push each other apart, and one waits rather than touch
   another (their footprint discs keep 0.1 m apart once apart).

Everything is float64 numpy and deterministic for the generator passed in. The tracks are
sampled at :data:`PLAN_RATE_HZ` on the scene clock (seconds since the flight's first sample);
:func:`uavcal_jax.sim.scene.target_states` interpolates them. The floor, the hall (grown to hold
the tracks) and keeping obstacles off the tracks and the lines of sight are
:func:`uavcal_jax.sim.scene_build.make_scene`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

__all__ = [
    "PLAN_RATE_HZ",
    "FollowRequest",
    "aim_points",
    "follow_request",
    "plan_tracks",
    "viewing_floor_z",
]

#: Planning and track sample rate, Hz.
PLAN_RATE_HZ = 20.0
#: Preferred camera-to-aim distance per class id (car, person), metres.
PREFERRED_DISTANCE_M = (8.0, 4.0)
#: Score per unit of a ray's image offset from the centre (a fraction of the half height),
#: against ``|log(distance / preferred)|``.
CENTRE_WEIGHT = 0.6
#: Deepest floor below the flight's median camera height that :func:`viewing_floor_z` asks
#: for (a camera looking straight down), metres.
MAX_VIEWING_DEPTH_M = 8.0
#: Wander radius, a fraction of the footprint's width at the aim (clipped to 0.3-3 m).
WANDER = 0.12
#: Several targets spread across this fraction of the footprint's width either side of the
#: image centre line.
SLOT_SPREAD = 0.18
#: Below this speed (m/s) a car may back up.
CAR_REVERSE_SPEED = 4.0
#: Aim points farther than this are not used (the target would be a few pixels), metres.
MAX_AIM_DISTANCE_M = 60.0
#: Gaussian smoothing of the aim track (standard deviation), seconds.
AIM_SMOOTHING_S = 0.4
#: Own speed (m/s), acceleration (m/s^2) and turn rate (rad/s) limits per class (car, person).
CLASS_SPEED = (6.0, 1.6)
CLASS_ACCEL = (4.0, 3.0)
CLASS_TURN_RATE = (1.2, 4.0)
#: Steering gain towards the goal, 1/s.
GAIN = 1.2
#: Mean seconds between stops, and the range of a stop's length, seconds.
STOP_EVERY_S = 4.0
STOP_LENGTH_S = (0.8, 2.5)


@dataclass(frozen=True)
class FollowRequest:
    """What the planner needs from the flight.

    Attributes:
        n: targets to place.
        t: (K,) float64 scene seconds of the planning steps (``k / PLAN_RATE_HZ``).
        T_WC: (K, 4, 4) float64 left-camera-to-world poses at ``t``.
        intrinsics: (4,) pinhole ``fu, fv, cu, cv`` of the left camera, pixels (distortion is
            ignored: the aim needs no pixel accuracy).
        resolution: ``(width, height)`` of the left camera, pixels.
    """

    n: int
    t: np.ndarray
    T_WC: np.ndarray
    intrinsics: np.ndarray
    resolution: tuple[int, int]


def follow_request(traj, T_BS: np.ndarray, intrinsics, resolution, t0_ns: int, t1_ns: int,
                   n: int) -> FollowRequest | None:
    """The :class:`FollowRequest` of camera ``T_BS`` (4, 4) along ``traj`` (a
    :class:`~uavcal_jax.sim.trajectory.Trajectory`) over ``[t0_ns, t1_ns]`` (int ns; scene time
    0 at ``t0_ns``); ``None`` when ``n`` is 0."""
    if n <= 0:
        return None
    K = int(np.floor((t1_ns - t0_ns) * 1e-9 * PLAN_RATE_HZ + 1e-9)) + 1
    t = np.arange(K) / PLAN_RATE_HZ
    t_ns = np.minimum(t0_ns + np.round(t * 1e9).astype(np.int64), t1_ns)
    state = traj.state_ns(t_ns)
    T_WB = np.zeros((K, 4, 4))
    T_WB[:, :3, :3] = state.rotation
    T_WB[:, :3, 3] = state.position
    T_WB[:, 3, 3] = 1.0
    return FollowRequest(n=int(n), t=t, T_WC=T_WB @ np.asarray(T_BS, dtype=np.float64),
                         intrinsics=np.asarray(intrinsics, dtype=np.float64),
                         resolution=tuple(int(v) for v in resolution))


def _fill(values: np.ndarray, valid: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``values`` (K, D) with the invalid rows interpolated from the valid ones (held at the
    ends); ``fallback`` (K, D) where no row is valid."""
    if not valid.any():
        return fallback.copy()
    idx = np.arange(values.shape[0])
    return np.stack([np.interp(idx, idx[valid], values[valid, d])
                     for d in range(values.shape[1])], -1)


def aim_points(req: FollowRequest, floor_z: float, preferred_m: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Floor points the left camera looks at (step 1 of the module docstring).

    Returns:
        aim (K, 2) world xy (gaps filled, not smoothed), distance (K,) from the camera to the
        aim, metres, and valid (K,) bool: a ray of that step reached the floor.
    """
    fu, fv, cu, cv = req.intrinsics
    h = req.resolution[1]
    frac = np.linspace(-0.4, 0.8, 13)  # of the way to the top (< 0) / bottom (> 0) edge
    v = cv + np.where(frac < 0, frac * (cv + 0.5), frac * (h - 0.5 - cv))
    rays = np.stack([np.zeros_like(v), (v - cv) / fv, np.ones_like(v)], -1)  # (J, 3) camera
    R, c = req.T_WC[:, :3, :3], req.T_WC[:, :3, 3]
    d = np.einsum("kij,mj->kmi", R, rays)  # (K, J, 3) world directions
    dz = d[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(dz < -1e-6, (floor_z - c[:, None, 2]) / dz, np.inf)
    dist = s * np.linalg.norm(d, axis=-1)
    ok = np.isfinite(dist) & (dist > 0) & (dist <= MAX_AIM_DISTANCE_M)
    score = np.where(ok, np.abs(np.log(np.where(ok, dist, 1.0) / preferred_m))
                     + CENTRE_WEIGHT * np.abs(frac), np.inf)
    j = np.argmin(score, axis=1)
    k = np.arange(req.t.shape[0])
    valid = ok[k, j]
    hit = c[:, :2] + s[k, j, None] * d[k, j, :2]
    # no ray on the floor anywhere: stand in front of the camera's horizontal heading
    heading = R[:, :2, 2] / np.maximum(np.linalg.norm(R[:, :2, 2], axis=-1, keepdims=True), 1e-9)
    fallback = c[:, :2] + preferred_m * heading
    aim = _fill(np.where(valid[:, None], hit, 0.0), valid, fallback)
    dist_f = _fill(np.where(valid, dist[k, j], 0.0)[:, None], valid,
                   np.full((k.size, 1), preferred_m))[:, 0]
    return aim, dist_f, valid


def viewing_floor_z(req: FollowRequest, class_ids) -> float:
    """Highest floor z (world metres) at which the left camera, at its median height and median
    depression, sees the floor at the image centre no nearer than the largest preferred viewing
    distance of ``class_ids`` (:data:`PREFERRED_DISTANCE_M`); ``inf`` (no limit) when the
    median optical axis points above the horizon.

    A low flight with a camera pitched down sees a floor close below it: a car 3 m away fills
    half the image and leaves it at the top and bottom edges, which no follower (and no
    detector) is built for. The hall's floor, the simulator's own choice, goes down instead
    until the target can be seen whole, as it is from the heights followers fly at (PX4's
    follow-target mode defaults to 8 m above the target). Flights whose camera looks nearly
    level (EuRoC's rig) ask for a floor above the one the flight's clearance already sets.
    """
    preferred = max(PREFERRED_DISTANCE_M[int(c)] for c in np.atleast_1d(class_ids))
    axis_z = req.T_WC[:, 2, 2]  # world z of the optical axis (unit vector)
    depression = np.arcsin(np.clip(-float(np.median(axis_z)), -1.0, 1.0))
    if depression <= 0.0:
        return float("inf")
    depth = min(preferred * np.sin(depression), MAX_VIEWING_DEPTH_M)
    return float(np.median(req.T_WC[:, 2, 3]) - depth)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def plan_tracks(req: FollowRequest, floor_z: float, rng: np.random.Generator,
                class_ids, half_extents) -> np.ndarray:
    """Ground tracks of ``req.n`` follow targets (steps 1-3 of the module docstring).

    Args:
        req: the flight's left camera over time.
        floor_z: world z of the floor, metres.
        rng: draws the wander, the stops and the turns.
        class_ids: (n,) class ids (0 car, 1 person).
        half_extents: (n, 3) the targets' half sizes, metres.

    Returns:
        (n, K, 3) float64 ``x, y, yaw`` (world metres; radians, unwrapped: continuous in time)
        of each target's box centre at ``req.t``.
    """
    n, K = req.n, req.t.shape[0]
    dt = 1.0 / PLAN_RATE_HZ
    class_ids = np.asarray(class_ids, dtype=np.int64).reshape(n)
    half = np.asarray(half_extents, dtype=np.float64).reshape(n, 3)
    reach = np.hypot(half[:, 0], half[:, 1])
    sigma = AIM_SMOOTHING_S * PLAN_RATE_HZ
    fu, w = req.intrinsics[0], req.resolution[0]

    goals, aim_vel = np.zeros((n, K, 2)), np.zeros((n, K, 2))
    # the camera's horizontal right axis: lateral slots when several targets share the view
    right = req.T_WC[:, :2, 0] / np.maximum(
        np.linalg.norm(req.T_WC[:, :2, 0], axis=-1, keepdims=True), 1e-9)
    right = gaussian_filter1d(right, sigma, axis=0, mode="nearest")
    spacing = 2.0 * reach.max() + 0.6
    # slots across the view (a fraction of the footprint's width), so that targets side by
    # side do not hide one another
    slots = (np.arange(n) - 0.5 * (n - 1)) * (2 * SLOT_SPREAD / max(n - 1, 1))
    for i in range(n):
        aim, dist, _ = aim_points(req, floor_z, PREFERRED_DISTANCE_M[class_ids[i]])
        aim = gaussian_filter1d(aim, sigma, axis=0, mode="nearest")
        dist = gaussian_filter1d(dist, sigma, mode="nearest")
        aim_vel[i] = np.gradient(aim, dt, axis=0)
        width = dist * w / fu  # the footprint's width at the aim, metres
        radius = np.clip(WANDER * width, 0.3, 3.0)
        periods = rng.uniform(5.0, 14.0, (2, 2))
        phases = rng.uniform(-np.pi, np.pi, (2, 2))
        amps = rng.uniform(0.3, 0.7, (2, 2))
        wander = np.stack([sum(amps[m, a] * np.sin(2 * np.pi * req.t / periods[m, a]
                                                      + phases[m, a]) for m in range(2))
                           for a in range(2)], -1)
        goals[i] = aim + radius[:, None] * wander + (slots[i] * width)[:, None] * right

    speed_cls = np.array([CLASS_SPEED[c] for c in class_ids])
    accel = np.array([CLASS_ACCEL[c] for c in class_ids])
    turn = np.array([CLASS_TURN_RATE[c] for c in class_ids])
    # stops: start times from exponential gaps, lengths uniform
    stops = []
    for _ in range(n):
        starts, t_next = [], 1.0 + rng.exponential(STOP_EVERY_S)
        while t_next < req.t[-1]:
            length = rng.uniform(*STOP_LENGTH_S)
            starts.append((t_next, t_next + length, rng.uniform(-np.pi, np.pi)))
            t_next += length + rng.exponential(STOP_EVERY_S)
        stops.append(starts)

    p = goals[:, 0].copy()
    v0 = aim_vel[:, 0]
    psi = np.where(np.linalg.norm(v0, axis=-1) > 0.2, np.arctan2(v0[:, 1], v0[:, 0]),
                   rng.uniform(-np.pi, np.pi, n))
    speed = np.minimum(np.linalg.norm(v0, axis=-1), speed_cls)
    out = np.zeros((n, K, 3))
    stop_at = [None] * n  # (end time, turn heading, stop position) while stopped
    stop_idx = [0] * n
    for k in range(K):
        t = req.t[k]
        out[:, k, :2], out[:, k, 2] = p, psi
        if k == K - 1:
            break
        for i in range(n):
            err = goals[i, k] - p[i]
            want = aim_vel[i, k] + GAIN * err
            for j in range(n):  # keep apart from the other follow targets
                if j != i:
                    gap = p[i] - p[j]
                    dij = float(np.linalg.norm(gap))
                    room = reach[i] + reach[j] + 1.0
                    if dij < room:
                        want = want + 4.0 * (room - dij) * gap / max(dij, 1e-6)
            cap = max(speed_cls[i], 1.3 * float(np.linalg.norm(aim_vel[i, k])) + 0.5)
            s_want = min(float(np.linalg.norm(want)), cap)
            # stops: begin on schedule when the camera lingers, end on time or when the goal
            # runs off (the target would leave the view)
            lingering = float(np.linalg.norm(aim_vel[i, k])) < 0.8
            plan = stops[i]
            while stop_idx[i] < len(plan) and plan[stop_idx[i]][1] < t:
                stop_idx[i] += 1
            if stop_at[i] is None and stop_idx[i] < len(plan) and plan[stop_idx[i]][0] <= t \
                    and lingering:
                end, heading = plan[stop_idx[i]][1], plan[stop_idx[i]][2]
                stop_at[i] = (end, heading)
                stop_idx[i] += 1
            if stop_at[i] is not None and (t >= stop_at[i][0] or float(np.linalg.norm(err)) >
                                           max(1.5, 0.5 * spacing) or not lingering):
                stop_at[i] = None
            if stop_at[i] is not None:
                s_want = 0.0
                psi_want = psi[i] + (_wrap(stop_at[i][1] - psi[i]) if class_ids[i] == 1
                                     else 0.0)  # a person turns in place; a car waits
            elif s_want > 0.15:
                psi_want = np.arctan2(want[1], want[0])
            else:
                psi_want, s_want = psi[i], 0.0
            sign = 1.0
            if class_ids[i] == 0 and s_want < CAR_REVERSE_SPEED and speed[i] <= 0.5 and abs(
                    _wrap(psi_want - psi[i])) > 0.5 * np.pi:
                sign, psi_want = -1.0, psi_want + np.pi  # back up: face away from the goal
            d_psi = float(np.clip(_wrap(psi_want - psi[i]), -turn[i] * dt, turn[i] * dt))
            psi[i] += d_psi
            s_cmd = sign * s_want * max(np.cos(_wrap(psi_want - psi[i])), 0.0)
            a_lim = max(accel[i], 2.0 * float(np.linalg.norm(
                aim_vel[i, min(k + 1, K - 1)] - aim_vel[i, k])) / dt)
            speed[i] += float(np.clip(s_cmd - speed[i], -a_lim * dt, a_lim * dt))
            step = p[i] + speed[i] * dt * np.array([np.cos(psi[i]), np.sin(psi[i])])
            if any(j != i and np.linalg.norm(step - p[j]) < min(
                    reach[i] + reach[j] + 0.1, np.linalg.norm(p[i] - p[j])) for j in range(n)):
                speed[i] = 0.0  # the move would touch another target: wait instead
            else:
                p[i] = step
    return out
