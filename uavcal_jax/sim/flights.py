"""Planned quadrotor flights as :class:`~uavcal_jax.sim.trajectory.Trajectory` objects.

* :func:`procedural_flight` draws a random quadrotor flight from a seed (hover, yaw turns,
  climbs and descents, straight legs, combined manoeuvres; 0-2 m/s) with the attitude a
  quadrotor needs for its acceleration: thrust (body z) along ``a + g e_z``
  (:data:`uavcal_jax.geometry.frames.GRAVITY`), heading from a smooth yaw profile.
* :func:`straight_flight`: hover, accelerate, cruise along a line of a given length, stop,
  hover.

A plan is a chain of (x, y, z, yaw) segments, each a smootherstep-ramped trapezoidal speed
profile within the configured limits; it becomes quintic position and yaw B-splines, and the
attitude follows from differential flatness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from uavcal_jax.geometry.frames import GRAVITY
from uavcal_jax.sim.trajectory import DEGREE, Trajectory, sign_continuous, uniform_knots

__all__ = ["FlightConfig", "procedural_flight", "quadrotor_attitude", "straight_flight"]


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) of (N, 3, 3) rotation matrices."""
    return Rotation.from_matrix(R).as_quat()[..., [3, 0, 1, 2]]


@dataclass(frozen=True)
class FlightConfig:
    """Limits and ranges of procedural flights (SI units, radians).

    Attributes:
        t0: time of the first sample, seconds.
        start_position: where the flight starts (hovering), world metres.
        start_yaw: heading at the start (``None``: drawn from the seed).
        max_speed, max_accel: horizontal speed / acceleration limits.
        max_vertical_speed, max_vertical_accel: vertical limits.
        max_yaw_rate, max_yaw_accel: heading rate / acceleration limits.
        area_half_size: the flight stays within ``start +- area_half_size`` horizontally.
        altitude_range: allowed heights (world z).
        leg_length: range of straight-leg lengths.
        climb: range of height changes for climbs/descents.
        yaw_turn: range of yaw-turn magnitudes.
        hover_time: range of hover durations.
        min_speed_fraction: each manoeuvre's speed limit is drawn in
            ``[min_speed_fraction, 1] * max``.
        knot_spacing: B-spline knot spacing of the position / yaw splines, seconds.
        attitude_rate_hz: rate at which the quadrotor attitude is computed and interpolated.
        rotor_drag: 1/s, the rotor drag coefficient per unit mass along body x and y (Faessler
            et al. 2018, "Differential flatness of quadrotor dynamics subject to rotor
            drag"): a force ``-m d v_B`` in the rotor plane that the thrust must tilt to
            balance; the accelerometer then reads ``-d v_B`` on x and y. 0: none (the
            thrust axis exactly along ``a + g e_z``); measured 0.3-0.6 on small quadrotors.
        thrust_tilt_deg: the thrust axis's constant tilt in the body frame about body x and
            y, degrees (propeller and frame asymmetry): the body leans so that the tilted
            axis carries the thrust, and the accelerometer reads it on x and y.
    """

    t0: float = 0.0
    start_position: tuple[float, float, float] = (0.0, 0.0, 1.5)
    start_yaw: float | None = None
    max_speed: float = 2.0
    max_accel: float = 1.5
    max_vertical_speed: float = 0.8
    max_vertical_accel: float = 1.0
    max_yaw_rate: float = 1.0
    max_yaw_accel: float = 1.5
    area_half_size: tuple[float, float] = (5.0, 5.0)
    altitude_range: tuple[float, float] = (0.8, 3.0)
    leg_length: tuple[float, float] = (1.0, 6.0)
    climb: tuple[float, float] = (0.3, 1.2)
    yaw_turn: tuple[float, float] = (math.pi / 6, math.pi)
    hover_time: tuple[float, float] = (0.5, 2.5)
    min_speed_fraction: float = 0.3
    knot_spacing: float = 0.1
    attitude_rate_hz: float = 100.0
    rotor_drag: float = 0.0
    thrust_tilt_deg: tuple[float, float] = (0.0, 0.0)


_RAMP_PEAK_ACCEL = 1.875  # max of d/ds (10 s^3 - 15 s^4 + 6 s^5)


def _ramp_integral(s: np.ndarray) -> np.ndarray:
    """Integral of the smootherstep ``10s^3 - 15s^4 + 6s^5`` from 0 to ``s`` (0.5 at s=1)."""
    s = np.clip(s, 0.0, 1.0)
    return s**4 * (2.5 - 3.0 * s + s * s)


@dataclass(frozen=True)
class _Segment:
    """Move by ``delta`` (x, y, z, yaw) in ``[t0, t0 + T]`` with a smooth trapezoid profile."""

    t0: float
    T: float
    T_ramp: float
    start: np.ndarray
    delta: np.ndarray

    def progress(self, t: np.ndarray) -> np.ndarray:
        """Normalised progress u(t) in [0, 1]; velocity is a smootherstep-ramped trapezoid."""
        if self.T_ramp <= 0.0:
            return np.ones_like(t)
        tau = np.clip(t - self.t0, 0.0, self.T)
        c = self.T - self.T_ramp  # distance / cruise speed, for unit distance
        r = self.T_ramp
        up = (r / c) * _ramp_integral(tau / r)
        mid = (0.5 * r + (tau - r)) / c
        down = 1.0 - (r / c) * _ramp_integral((self.T - tau) / r)
        return np.where(tau < r, up, np.where(tau <= self.T - r, mid, down))


def _profile_times(dists_limits: list[tuple[float, float, float]]) -> tuple[float, float]:
    """Total time T and ramp time of a shared profile meeting every (distance, v, a) limit.

    The unit profile has peak speed ``1 / c`` and peak acceleration ``1.875 / (c T_r)`` with
    ``c = T - T_r``; each axis scales them by its distance.
    """
    c = max((d / v for d, v, _ in dists_limits if d > 0), default=0.0)
    if c <= 0.0:
        return 0.0, 0.0
    r = max(_RAMP_PEAK_ACCEL * d / (a * c) for d, _, a in dists_limits if d > 0)
    if r > c:  # no cruise phase: c = T_r, both limits hold
        c = r = math.sqrt(max(_RAMP_PEAK_ACCEL * d / a for d, _, a in dists_limits if d > 0))
    return c + r, r


class _Plan:
    """Piecewise (x, y, z, yaw) plan made of hover and move segments."""

    def __init__(self, t0: float, start: np.ndarray):
        self.t = t0
        self.state = np.asarray(start, dtype=np.float64)
        self.segments: list[_Segment] = []

    def hover(self, T: float) -> None:
        self.segments.append(_Segment(self.t, T, 0.0, self.state.copy(), np.zeros(4)))
        self.t += T

    def move(self, delta: np.ndarray, v_h: float, a_h: float, v_z: float, a_z: float,
             v_yaw: float, a_yaw: float) -> None:
        delta = np.asarray(delta, dtype=np.float64)
        T, r = _profile_times([(float(np.hypot(delta[0], delta[1])), v_h, a_h),
                               (abs(float(delta[2])), v_z, a_z),
                               (abs(float(delta[3])), v_yaw, a_yaw)])
        if T <= 0.0:
            return
        self.segments.append(_Segment(self.t, T, r, self.state.copy(), delta))
        self.t += T
        self.state = self.state + delta

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.empty(t.shape + (4,))
        starts = np.array([s.t0 for s in self.segments])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.segments) - 1)
        for k in np.unique(idx):
            seg = self.segments[k]
            sel = idx == k
            out[sel] = seg.start + seg.progress(t[sel])[:, None] * seg.delta
        before = t < self.segments[0].t0
        out[before] = self.segments[0].start
        return out


#: Most fixed-point passes of :func:`quadrotor_attitude` with rotor drag (the drag depends on
#: the attitude it tilts; each pass shrinks the error by about ``d |v| / g``, 0.1 at 2 m/s and
#: d = 0.5), and the change of the axis at which they stop, rad.
DRAG_PASSES, DRAG_TOLERANCE = 30, 1e-12


def _thrust_frame(thrust: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) body-to-world rotations with body z along ``thrust`` (N, 3) and body x in
    the vertical plane of heading ``yaw`` (N,)."""
    z_b = thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
    x_c = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
    y_b = np.cross(z_b, x_c)
    y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
    x_b = np.cross(y_b, z_b)
    return np.stack([x_b, y_b, z_b], axis=2)


def quadrotor_attitude(accel: np.ndarray, velocity: np.ndarray, yaw: np.ndarray,
                       rotor_drag: float = 0.0,
                       thrust_tilt_deg: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(N, 3, 3) body-to-world rotations of a quadrotor flying ``accel`` and ``velocity``
    ((N, 3) world, m/s^2 and m/s) with heading ``yaw`` (N,) rad: the thrust balances
    ``a + g e_z`` and the rotor drag ``-d v_B`` on body x and y (``rotor_drag`` d, 1/s), and
    acts along the body's axis tilted by ``thrust_tilt_deg`` about body x then y
    (:class:`FlightConfig`)."""
    accel = np.asarray(accel, np.float64)
    velocity = np.asarray(velocity, np.float64)
    need = accel + np.array([0.0, 0.0, GRAVITY])
    R = _thrust_frame(need, yaw)
    if rotor_drag > 0.0:
        plane = np.diag([1.0, 1.0, 0.0])
        for _ in range(DRAG_PASSES):  # T z_B = a + g e_z + d R P R^T v
            v_body = np.einsum("nji,nj->ni", R, velocity)
            prev, R = R, _thrust_frame(
                need + rotor_drag * np.einsum("nij,jk,nk->ni", R, plane, v_body), yaw)
            if np.max(np.abs(R - prev)) < DRAG_TOLERANCE:
                break
    if any(thrust_tilt_deg):
        tilt = Rotation.from_euler("xy", np.radians(thrust_tilt_deg)).as_matrix()
        R = R @ tilt.T  # the body's tilted axis R_B (tilt e_z) now lies along the thrust
    return R


def _flatness_trajectory(plan: _Plan, t0: float, duration: float, config: FlightConfig,
                         name: str) -> Trajectory:
    """Quintic splines through the plan, and the quadrotor attitude it implies."""
    margin = 1.0
    h = config.knot_spacing
    t_ref_ns = int(round(t0 * 1e9))
    knots = uniform_knots(-margin, duration + margin, h)
    # Control points sampled at the Greville abscissae: the spline reproduces linear motion
    # exactly and smooths the plan by ~h.
    greville = np.array([knots[i + 1:i + DEGREE + 1].mean()
                         for i in range(len(knots) - DEGREE - 1)])
    ctrl = plan(t0 + greville)
    pos_spline = BSpline(knots, ctrl[:, :3], DEGREE)
    yaw_spline = BSpline(knots, ctrl[:, 3], DEGREE)

    n = int(math.ceil((duration + 2 * margin) * config.attitude_rate_hz)) + 1
    tau = np.linspace(-margin, duration + margin, n)
    R = quadrotor_attitude(pos_spline(tau, nu=2), pos_spline(tau, nu=1), yaw_spline(tau),
                           config.rotor_drag, config.thrust_tilt_deg)
    quat = sign_continuous(_matrix_to_quat(R))
    quat_spline = make_interp_spline(tau, quat, k=DEGREE)
    return Trajectory(float(t0), float(t0 + duration), pos_spline, quat_spline, t_ref_ns, name)


def procedural_flight(seed: int, duration: float,
                      config: FlightConfig = FlightConfig()) -> Trajectory:  # noqa: B008
    """A random, smooth, quadrotor-like flight, deterministic for ``seed``.

    The flight starts hovering at ``config.start_position`` and chains manoeuvres drawn with
    ``numpy.random.default_rng(seed)``: hovers, yaw turns, climbs/descents, straight legs
    (some facing their direction of travel, some with a simultaneous climb or yaw change), each
    with a smootherstep-ramped trapezoidal speed profile within the configured speed and
    acceleration limits, inside ``area_half_size`` and ``altitude_range``. The position and yaw
    plans become quintic B-splines; the attitude is the quadrotor's
    (:func:`quadrotor_attitude`): the thrust along ``a + g e_z`` (with ``config.rotor_drag``,
    plus the drag it balances; with ``config.thrust_tilt_deg``, carried by a tilted body
    axis), body x in the vertical plane of the heading.

    Args:
        seed: random seed (an int).
        duration: seconds (> 0).
        config: limits and ranges.
    """
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    rng = np.random.default_rng(seed)
    c = config
    start = np.asarray(c.start_position, dtype=np.float64)
    yaw0 = float(rng.uniform(-math.pi, math.pi)) if c.start_yaw is None else float(c.start_yaw)
    plan = _Plan(c.t0, np.array([*start, yaw0]))
    plan.hover(float(rng.uniform(1.0, 2.0)))
    lo_xy, hi_xy = start[:2] - np.asarray(c.area_half_size), start[:2] + np.asarray(
        c.area_half_size)
    z_lo, z_hi = c.altitude_range

    def speeds(v: float) -> float:
        return v * float(rng.uniform(c.min_speed_fraction, 1.0))

    def limits() -> tuple[float, ...]:
        return (speeds(c.max_speed), c.max_accel, speeds(c.max_vertical_speed),
                c.max_vertical_accel, speeds(c.max_yaw_rate), c.max_yaw_accel)

    def climb_delta() -> float:
        z = plan.state[2]
        dz = float(rng.uniform(*c.climb)) * (1.0 if rng.random() < 0.5 else -1.0)
        if not z_lo <= z + dz <= z_hi:
            dz = -dz
        return float(np.clip(z + dz, z_lo, z_hi) - z)

    def leg_delta() -> np.ndarray:
        xy = plan.state[:2]
        for _ in range(8):
            heading = float(rng.uniform(-math.pi, math.pi))
            d = np.array([math.cos(heading), math.sin(heading)]) * float(
                rng.uniform(*c.leg_length))
            target = np.clip(xy + d, lo_xy, hi_xy)
            if np.linalg.norm(target - xy) >= 0.5 * c.leg_length[0]:
                return target - xy
        to_centre = start[:2] - xy
        return to_centre if np.linalg.norm(to_centre) > 1e-6 else np.array([c.leg_length[0], 0])

    def wrap_turn(target_yaw: float) -> float:
        return (target_yaw - plan.state[3] + math.pi) % (2 * math.pi) - math.pi

    while plan.t < c.t0 + duration + 2.0:
        kind = rng.choice(["hover", "yaw", "climb", "leg", "leg_facing", "combined"],
                          p=[0.12, 0.16, 0.14, 0.22, 0.18, 0.18])
        if kind == "hover":
            plan.hover(float(rng.uniform(*c.hover_time)))
        elif kind == "yaw":
            turn = float(rng.uniform(*c.yaw_turn)) * (1.0 if rng.random() < 0.5 else -1.0)
            plan.move([0, 0, 0, turn], *limits())
        elif kind == "climb":
            plan.move([0, 0, climb_delta(), 0], *limits())
        elif kind == "leg":
            d = leg_delta()
            plan.move([d[0], d[1], 0, 0], *limits())
        elif kind == "leg_facing":
            d = leg_delta()
            plan.move([0, 0, 0, wrap_turn(math.atan2(d[1], d[0]))], *limits())
            plan.move([d[0], d[1], 0, 0], *limits())
        else:  # a leg with a simultaneous climb and heading change
            d = leg_delta()
            dz = climb_delta() if rng.random() < 0.7 else 0.0
            dyaw = float(rng.uniform(-1.0, 1.0)) * c.yaw_turn[1] * 0.5
            plan.move([d[0], d[1], dz, dyaw], *limits())
        if rng.random() < 0.3:
            plan.hover(float(rng.uniform(0.2, 1.0)))
    return _flatness_trajectory(plan, c.t0, float(duration), c, f"procedural-seed-{seed}")


def straight_flight(length: float, speed: float = 1.0,
                    config: FlightConfig = FlightConfig(),  # noqa: B008
                    *, heading: float = 0.0, hover_time: float = 2.0) -> Trajectory:
    """Hover, fly ``length`` metres in a straight line at ``speed``, stop and hover.

    The body faces ``heading`` (radians from world x; the line runs along it), starting at
    ``config.start_position``. Speed ramps with ``config.max_accel`` (smootherstep ramps, so
    acceleration is continuous); the cruise speed is exactly ``speed`` when the line is long
    enough to reach it.
    """
    if length <= 0 or speed <= 0:
        raise ValueError("length and speed must be positive")
    start = np.asarray(config.start_position, dtype=np.float64)
    plan = _Plan(config.t0, np.array([*start, heading]))
    plan.hover(hover_time)
    d = length * np.array([math.cos(heading), math.sin(heading)])
    plan.move([d[0], d[1], 0.0, 0.0], speed, config.max_accel, 1.0, 1.0, 1.0, 1.0)
    plan.hover(hover_time + 3.0)
    duration = plan.t - config.t0 - 3.0
    return _flatness_trajectory(plan, config.t0, duration, config,
                                f"straight-{length:g}m-{speed:g}mps")
