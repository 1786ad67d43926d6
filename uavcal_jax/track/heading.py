"""A target's heading over time: which of the box model's candidate headings to believe.

One frame's box shape often fits two headings (mirror images about the line of sight), and a
slow target's velocity points anywhere. Together over time they agree: a discrete Bayes
filter (the forward pass of a hidden Markov model) over the candidate headings
(:data:`uavcal_jax.track.box_model.CANDIDATE_HEADINGS`, axial: ``h`` and ``h + pi`` are one box),
causal as a live follower runs it:

* motion: the heading diffuses between observations with a standard deviation that grows with
  the elapsed time, ``turn_rate * dt`` (a car turns at most about 1.2 rad/s), floored at half
  the grid's spacing;
* the box's shape: ``exp(-mismatch / (2 shape_sigma^2))`` with ``mismatch`` the relative
  squared corner error of :func:`~uavcal_jax.track.box_model.box_centre_candidates`;
* the velocity, where the target moves faster than ``min_speed``: an axial von Mises
  ``exp(kappa cos(2 (h - atan2(v_y, v_x))))``.

The belief's spread over the candidates' centres is the heading's share of the located
point's covariance (:func:`heading_spread`), so the position filter weighs an ambiguous view
less. NumPy: 16 states cost tens of microseconds a frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uavcal_jax.track.box_model import CANDIDATE_HEADINGS

__all__ = ["HeadingConfig", "heading_from_velocity", "heading_spread", "heading_step",
           "track_heading", "uniform_belief"]


@dataclasses.dataclass(frozen=True)
class HeadingConfig:
    """Settings of :func:`track_heading` (module docstring).

    Attributes:
        min_speed: m/s; below this horizontal speed the velocity says nothing of the heading.
        turn_rate: rad/s, the heading's diffusion per second (its standard deviation).
        shape_sigma: the box shape's relative corner error (of the box's diagonal) one standard
            deviation stands for (detector jitter and the model's size error).
        velocity_kappa: the velocity's axial von Mises concentration (2: about 30 degrees).
    """

    min_speed: float = 0.5
    turn_rate: float = 1.0
    shape_sigma: float = 0.05
    velocity_kappa: float = 2.0

    def __post_init__(self):
        if self.min_speed < 0.0 or self.turn_rate <= 0.0 or self.shape_sigma <= 0.0:
            raise ValueError("heading: need min_speed >= 0, turn_rate > 0, shape_sigma > 0")


def heading_from_velocity(velocity, min_speed: float = 0.5) -> np.ndarray:
    """Per frame, the heading ``atan2(v_y, v_x)`` (radians) of a world velocity (T, 3) m/s,
    NaN where slower than ``min_speed`` horizontally (or unknown)."""
    v = np.asarray(velocity, np.float64).reshape(-1, 3)
    speed = np.hypot(v[:, 0], v[:, 1])
    fast = np.isfinite(speed) & (speed >= min_speed)
    return np.where(fast, np.arctan2(v[:, 1], v[:, 0]), np.nan)


def _axial_gap(a, b):
    """|a - b| folded to an axial difference in ``[0, pi/2]``."""
    d = np.mod(np.asarray(a) - np.asarray(b) + np.pi / 2, np.pi) - np.pi / 2
    return np.abs(d)


def uniform_belief() -> np.ndarray:
    """(H,) the belief before any observation: every candidate heading alike."""
    return np.full(len(CANDIDATE_HEADINGS), 1.0 / len(CANDIDATE_HEADINGS))


def heading_step(belief, dt: float, mismatch, velocity_heading: float,
                 config: HeadingConfig = HeadingConfig()) -> np.ndarray:
    """One observation of :func:`track_heading`: the belief (H,) ``dt`` seconds after
    ``belief`` (H,), given the shape ``mismatch`` (H,) (NaN: no shape) and the velocity's
    heading (radians, NaN: unknown or slow)."""
    grid = np.asarray(CANDIDATE_HEADINGS, np.float64)
    sigma = max(config.turn_rate * max(dt, 0.0), 0.5 * np.pi / grid.size)
    moved = np.exp(-0.5 * (_axial_gap(grid[:, None], grid[None, :]) / sigma) ** 2)
    prior = (moved / moved.sum(axis=0, keepdims=True)) @ np.asarray(belief, np.float64)
    log_like = np.zeros(grid.size)
    mismatch = np.asarray(mismatch, np.float64)
    if np.all(np.isfinite(mismatch)):
        log_like -= 0.5 * mismatch / config.shape_sigma ** 2
    if np.isfinite(velocity_heading):
        log_like += config.velocity_kappa * np.cos(2.0 * (grid - velocity_heading))
    posterior = prior * np.exp(log_like - np.max(log_like))
    return posterior / posterior.sum()


def track_heading(times_s, mismatch, velocity_heading,
                  config: HeadingConfig = HeadingConfig()) -> tuple[np.ndarray, np.ndarray]:
    """The most probable candidate heading at each observation (module docstring).

    Args:
        times_s: (R,) the observations' times, seconds, increasing.
        mismatch: (R, H) the box shape's mismatch per candidate heading
            (:func:`~uavcal_jax.track.box_model.box_centre_candidates`).
        velocity_heading: (R,) the heading of the target's velocity known before each
            observation, radians, NaN where it is unknown or slow.
        config: :class:`HeadingConfig`.

    Returns:
        ``(chosen, beliefs)``: (R,) int, the index into
        :data:`~uavcal_jax.track.box_model.CANDIDATE_HEADINGS` of each observation's most probable
        heading, and (R, H) the beliefs it was chosen from.
    """
    times = np.asarray(times_s, np.float64)
    beliefs = np.zeros((times.shape[0], len(CANDIDATE_HEADINGS)))
    belief = uniform_belief()
    for r in range(times.shape[0]):
        dt = times[r] - times[r - 1] if r else 0.0
        belief = beliefs[r] = heading_step(belief, dt, mismatch[r], velocity_heading[r], config)
    return np.argmax(beliefs, axis=1), beliefs


def heading_spread(centres, belief, chosen):
    """The covariance (..., 3, 3) m^2 the heading's uncertainty adds to a chosen centre: the
    candidates' centres (..., H, 3) about the chosen one (...,) (an index), weighed by the
    belief (..., H); add it to the localisation's own covariance."""
    centres = np.asarray(centres, np.float64)
    chosen_centre = np.take_along_axis(centres, np.asarray(chosen)[..., None, None], axis=-2)
    d = centres - chosen_centre
    return np.einsum("...h,...hi,...hj->...ij", np.asarray(belief, np.float64), d, d)
