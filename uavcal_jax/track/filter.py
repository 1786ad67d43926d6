"""A constant-velocity Kalman filter on a target's world position: one ``lax.scan`` over frames.

State ``x = [p, v]`` (6,): world position (m) and velocity (m/s). Motion model: constant
velocity driven by continuous white-noise acceleration of power spectral density ``q``
(m^2/s^3) per axis, discretised exactly over ``dt`` (Bar-Shalom, Li & Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, sec. 6.2.2, the "continuous white noise
acceleration" (CWNA) model; not the piecewise-constant "discrete white noise acceleration"
form of sec. 6.3.2)::

    F = [[I, dt I], [0, I]]
    Q = [[dt^3/3 D, dt^2/2 D], [dt^2/2 D, dt D]],  D = diag(q_x, q_y, q_z)

The world is gravity-aligned (z up). A target on the ground does not climb: with
``vertical_accel_psd = 0`` and ``vertical_velocity_sigma = 0`` its vertical velocity stays
zero, and its height may instead wander as a random walk of PSD ``height_walk_psd`` (m^2/s,
added to ``Q``'s height entry as ``height_walk_psd * dt``). The height still follows the
measurements, whose height error changes with the view (a stiff height would turn it into a
range error along the slanted line of sight), but height errors of boxes cut by the image
border are no longer taken up as a climb that a coasting prediction flies off with.

Measurement: the position, ``z = p + n``, ``n ~ N(0, R_k)`` with a per-frame ``R_k`` (from
:mod:`uavcal_jax.track.locate`). A measurement whose squared Mahalanobis distance to the
prediction, ``y^T S^-1 y``, exceeds the chi-square quantile (3 degrees of freedom) of
``gate_probability`` is gated out (not used), unless ``reinit_after_gated`` measurements in a
row were: then the track has left the target (a turn the constant-velocity model did not
follow) rather than met outliers, and the filter re-initialises from the measurement. While no
measurement is used the filter only predicts, the position moving with the velocity for at
most ``coast_after`` seconds after the last used measurement and held after that (a car that
left the image at a turn or a stop is not flown off to in a straight line; the covariance
keeps growing); ``lost_after`` seconds after the last used
measurement the target is lost: the output holds the last prediction and the next valid
measurement re-initialises the filter (position from it, velocity zero with
``init_velocity_sigma``), ungated.

Everything is jitted and fixed-shape: inputs ``(T, ...)`` per frame, with a valid mask.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from scipy.stats import chi2

__all__ = [
    "LOST",
    "PREDICTING",
    "STATUS_NAMES",
    "TRACKING",
    "UNSEEN",
    "FilterConfig",
    "FilterOutput",
    "filter_start",
    "filter_step",
    "transition",
    "white_noise_acceleration_q",
]

#: Per-frame status codes; ``STATUS_NAMES[code]`` is the word. ``TRACKING``: a measurement
#: was used this frame; ``PREDICTING``: none was (unseen or gated out), prediction only;
#: ``LOST``: unseen for longer than ``lost_after`` (output held at the last prediction);
#: ``UNSEEN``: no measurement yet (no estimate; the output is NaN).
TRACKING, PREDICTING, LOST, UNSEEN = 0, 1, 2, 3
STATUS_NAMES = ("tracking", "predicting", "lost", "unseen")


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Settings of the target filter (hashable: the jitted filter compiles once per config).

    Attributes:
        accel_psd: ``q``, the power spectral density of the target's white-noise
            acceleration, m^2/s^3 per axis (1.0: a walking person or a slow car; the
            acceleration std over 1 s is about ``sqrt(q)`` m/s^2).
        vertical_accel_psd: the world z axis's ``q`` instead (``None``: ``accel_psd``, the
            same on every axis).
        gate_probability: the measurement gate keeps this much probability of a consistent
            measurement (chi-square, 3 degrees of freedom; 0.997 -> d^2 <= 14.16).
        lost_after: seconds without a used measurement before the target is lost.
        init_velocity_sigma: velocity standard deviation at (re-)initialisation, m/s.
        vertical_velocity_sigma: the world z axis's instead (``None``:
            ``init_velocity_sigma``); with a small ``vertical_accel_psd`` a climb taken up
            from the first noisy heights would stay for long.
        height_walk_psd: the PSD of a random walk of the height, m^2/s (module docstring).
        reinit_after_gated: this many gated measurements in a row re-initialise the filter
            from the last of them (0: never).
        coast_after: seconds after the last used measurement during which the prediction
            moves with the velocity; later it is held (``inf``: always moves).
    """

    accel_psd: float = 1.0
    vertical_accel_psd: float | None = None
    gate_probability: float = 0.997
    lost_after: float = 2.0
    init_velocity_sigma: float = 2.0
    vertical_velocity_sigma: float | None = None
    height_walk_psd: float = 0.0
    reinit_after_gated: int = 5
    coast_after: float = float("inf")

    def __post_init__(self):
        if self.accel_psd < 0.0:
            raise ValueError(f"accel_psd must be >= 0, got {self.accel_psd}")
        for name in ("vertical_accel_psd", "vertical_velocity_sigma", "height_walk_psd"):
            value = getattr(self, name)
            if value is not None and value < 0.0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if self.lost_after <= 0.0:
            raise ValueError(f"lost_after must be > 0, got {self.lost_after}")
        if not self.coast_after >= 0.0:
            raise ValueError(f"coast_after must be >= 0, got {self.coast_after}")
        if self.reinit_after_gated < 0:
            raise ValueError(f"reinit_after_gated must be >= 0, got {self.reinit_after_gated}")

    @property
    def axis_psd(self) -> tuple[float, float, float]:
        """``(q_x, q_y, q_z)``, m^2/s^3: the world axes' acceleration PSDs."""
        return _per_axis(self.accel_psd, self.vertical_accel_psd)

    @property
    def axis_velocity_sigma(self) -> tuple[float, float, float]:
        """The world axes' velocity standard deviations at (re-)initialisation, m/s."""
        return _per_axis(self.init_velocity_sigma, self.vertical_velocity_sigma)

    @property
    def gate(self) -> float:
        """The squared-Mahalanobis gate: chi-square(3) quantile of ``gate_probability``."""
        return float(chi2.ppf(self.gate_probability, df=3))


class FilterOutput(NamedTuple):
    """Per-frame outputs, each with a leading frame axis ``T``.

    Attributes:
        position: (T, 3) filtered world position, metres (NaN while ``UNSEEN``).
        velocity: (T, 3) filtered velocity, m/s.
        covariance: (T, 6, 6) state covariance.
        status: (T,) int, ``TRACKING`` / ``PREDICTING`` / ``LOST`` / ``UNSEEN``.
        gated: (T,) bool, a valid measurement was rejected by the gate.
        nis: (T,) the measurement's squared Mahalanobis distance (NaN without one).
    """

    position: jax.Array
    velocity: jax.Array
    covariance: jax.Array
    status: jax.Array
    gated: jax.Array
    nis: jax.Array


def _per_axis(horizontal: float, vertical: float | None) -> tuple[float, float, float]:
    """``(x, y, z)``: ``horizontal`` on x and y, ``vertical`` on z (``None``: ``horizontal``)."""
    return (horizontal, horizontal, horizontal if vertical is None else vertical)


def transition(dt) -> jax.Array:
    """(6, 6) the constant-velocity transition ``[[I, dt I], [0, I]]``."""
    dt = jnp.asarray(dt)
    eye = jnp.eye(3, dtype=dt.dtype)
    return jnp.block([[eye, dt * eye], [jnp.zeros_like(eye), eye]])


def white_noise_acceleration_q(dt, q) -> jax.Array:
    """(6, 6) process noise of continuous white-noise acceleration integrated over ``dt``
    seconds: ``[[dt^3/3 D, dt^2/2 D], [dt^2/2 D, dt D]]`` with ``D = diag(q)``; ``q`` the PSD
    (m^2/s^3), a scalar (every axis) or (3,) per axis."""
    dt = jnp.asarray(dt)
    D = jnp.diag(jnp.broadcast_to(jnp.asarray(q, dt.dtype), (3,)))
    return jnp.block([[dt ** 3 / 3.0 * D, dt ** 2 / 2.0 * D],
                      [dt ** 2 / 2.0 * D, dt * D]])


class _Carry(NamedTuple):
    x: jax.Array  # (6,)
    P: jax.Array  # (6, 6)
    t: jax.Array  # time of the state
    t_used: jax.Array  # time of the last used measurement
    active: jax.Array  # bool: initialised and not lost
    gated_run: jax.Array  # int: measurements gated in a row


def _step(config: FilterConfig, carry: _Carry, frame):
    t, z, R, valid = frame
    dtype = carry.x.dtype
    valid = valid & jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(R))
    z = jnp.where(valid, z, 0.0)
    R = jnp.where(valid, R, jnp.eye(3, dtype=dtype))

    # predict (only meaningful while active; lost/unseen states are held, not propagated)
    dt = jnp.maximum(t - carry.t, 0.0)
    # the mean moves only until coast_after past the last used measurement (t_used is NaN
    # before the first, when nothing is active)
    t_stop = jnp.where(jnp.isnan(carry.t_used), t, carry.t_used + config.coast_after)
    dt_move = jnp.clip(jnp.minimum(t, t_stop) - carry.t, 0.0, dt)
    x_pred = transition(dt_move) @ carry.x
    F = transition(dt)
    P_pred = (F @ carry.P @ F.T + white_noise_acceleration_q(dt, jnp.asarray(config.axis_psd))
              ).at[2, 2].add(config.height_walk_psd * dt)
    lost_now = carry.active & (t - carry.t_used > config.lost_after)
    active = carry.active & ~lost_now

    # gate and update
    H = jnp.eye(3, 6, dtype=dtype)
    y = z - x_pred[:3]
    S = P_pred[:3, :3] + R
    S = 0.5 * (S + S.T)
    cho = jax.scipy.linalg.cho_factor(S)
    nis = y @ jax.scipy.linalg.cho_solve(cho, y)
    gated = active & valid & (nis > config.gate)
    reinit = gated & (config.reinit_after_gated > 0) & (
        carry.gated_run + 1 >= config.reinit_after_gated)
    gated = gated & ~reinit
    use = active & valid & ~gated & ~reinit
    K = jax.scipy.linalg.cho_solve(cho, H @ P_pred).T  # P H^T S^-1
    x_upd = x_pred + K @ y
    IKH = jnp.eye(6, dtype=dtype) - K @ H
    P_upd = IKH @ P_pred @ IKH.T + K @ R @ K.T  # Joseph form: stays symmetric positive

    # (re-)initialise from a valid measurement when not active (unseen or lost)
    init = (~active & valid) | reinit
    x_init = jnp.concatenate([z, jnp.zeros(3, dtype)])
    P_init = jnp.zeros((6, 6), dtype).at[:3, :3].set(R).at[3:, 3:].set(
        jnp.diag(jnp.asarray(config.axis_velocity_sigma, dtype) ** 2))

    x = jnp.where(init, x_init, jnp.where(use, x_upd, jnp.where(active, x_pred, carry.x)))
    P = jnp.where(init, P_init, jnp.where(use, P_upd, jnp.where(active, P_pred, carry.P)))
    P = 0.5 * (P + P.T)
    seen_ever = ~jnp.isnan(carry.t_used) | init
    t_used = jnp.where(init | use, t, carry.t_used)
    new_active = active | init
    status = jnp.where(init | use, TRACKING,
                       jnp.where(active, PREDICTING, jnp.where(seen_ever, LOST, UNSEEN)))
    gated_run = jnp.where(gated, carry.gated_run + 1, jnp.where(init | use, 0, carry.gated_run))
    new_carry = _Carry(x, P, jnp.where(new_active, t, carry.t), t_used, new_active,
                       gated_run.astype(jnp.int32))
    position = jnp.where(seen_ever, x[:3], jnp.nan)
    velocity = jnp.where(seen_ever, x[3:], jnp.nan)
    out = FilterOutput(position, velocity, P, status.astype(jnp.int32), gated,
                       jnp.where(active & valid, nis, jnp.nan))
    return new_carry, out


def filter_start(t, dtype) -> _Carry:
    """The filter's state before its first frame at time ``t`` (seconds): nothing seen."""
    return _Carry(x=jnp.zeros(6, dtype), P=jnp.eye(6, dtype=dtype), t=jnp.asarray(t, dtype),
                  t_used=jnp.asarray(jnp.nan, dtype), active=jnp.asarray(False),
                  gated_run=jnp.zeros((), jnp.int32))


@functools.partial(jax.jit, static_argnames="config")
def filter_step(carry: _Carry, t, z, R, valid, config: FilterConfig = FilterConfig()
                ) -> tuple[_Carry, FilterOutput]:
    """One frame of the filter: the state after the frame at time
    ``t`` with measurement ``z`` (3,), covariance ``R`` (3, 3) and ``valid`` () bool, and the
    frame's :class:`FilterOutput` (no frame axis). Start from :func:`filter_start`."""
    dtype = carry.x.dtype
    return _step(config, carry, (jnp.asarray(t, dtype), jnp.asarray(z, dtype),
                                 jnp.asarray(R, dtype), jnp.asarray(valid, bool)))
