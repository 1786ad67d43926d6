"""Failure detection after a window solve (VINS-Fusion's ``failureDetection``, which it ships
disabled; here it runs): a pure function of the solved newest frame, its IMU prediction, the
solve's cost and the landmark count, returning a typed :class:`Failure` or ``None`` when the
window is healthy. The limits are :class:`~uavcal_jax.vio.config.FailureLimits`.
"""

from __future__ import annotations

import enum

import numpy as np

from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import FailureLimits

__all__ = ["Failure", "blind_frames", "check_failure", "chi2_bound", "cost_excess_frames"]


class Failure(enum.Enum):
    """Why the window failed; the value is the estimate's ``reason``."""

    NAN = "nan"  # a non-finite state or cost
    BIAS = "bias"  # a bias estimate beyond its sane norm
    JUMP = "jump"  # the solved frame far from its IMU prediction
    COST = "cost"  # the cost per residual row blew up
    VELOCITY = "velocity"  # the solved velocity far from its IMU prediction
    CHI2 = "chi2"  # the normalised window cost above its chi-square bound for several frames
    BLIND = "blind"  # too long without enough landmarks


def blind_frames(previous: int, active_landmarks: int, limits: FailureLimits) -> int:
    """Consecutive frames with fewer than ``limits.min_landmarks`` active landmarks, this one
    included (``previous`` the count before it)."""
    return previous + 1 if active_landmarks < limits.min_landmarks else 0


def chi2_bound(rows: int, limits: FailureLimits) -> float:
    """The largest ``2 cost`` a consistent window of ``rows`` residual rows passes: the
    chi-square quantile by the normal approximation, ``rows + z sqrt(2 rows)`` with ``z =
    limits.chi2_z``, times ``limits.chi2_scale`` (the whitening's pixel sigma overstates a
    healthy front end's noise, so a consistent window sits well below ``rows``)."""
    r = max(int(rows), 1)
    return limits.chi2_scale * (r + limits.chi2_z * np.sqrt(2.0 * r))


def cost_excess_frames(previous: int, cost: float, rows: int, limits: FailureLimits) -> int:
    """Consecutive frames whose window fails the chi-square test (``2 cost`` above
    :func:`chi2_bound`), this one included (``previous`` the count before it)."""
    return previous + 1 if 2.0 * cost > chi2_bound(rows, limits) else 0


def check_failure(solved: BodyState, predicted: BodyState, cost: float, rows: int, blind: int,
                  limits: FailureLimits, cost_excess: int = 0, velocity_check: bool = True
                  ) -> Failure | None:
    """The first failure, in the order of :class:`Failure`, or ``None``.

    Args:
        solved: the newest frame after the solve.  predicted: its IMU prediction.
        cost: the solved window cost.  rows: residual rows in use (the cost's divisor).
        blind: :func:`blind_frames` after this frame.
        limits: the thresholds.
        cost_excess: :func:`cost_excess_frames` after this frame (a window drifting off its
            measurements stays consistent with its IMU prediction, frame by frame, while its
            cost grows: this is the test that sees it).
        velocity_check: test the velocity against its prediction (off while a window's start
            is still an assumption, e.g. at rest, which its first solves correct by metres
            per second on a body already flying).
    """
    values = np.concatenate([solved.rotation.ravel(), solved.position, solved.velocity,
                             solved.bias_gyro, solved.bias_accel])
    if not (np.all(np.isfinite(values)) and np.isfinite(cost)):
        return Failure.NAN
    if (np.linalg.norm(solved.bias_gyro) > limits.max_bias_gyro
            or np.linalg.norm(solved.bias_accel) > limits.max_bias_accel):
        return Failure.BIAS
    cos = np.clip(0.5 * (np.trace(predicted.rotation.T @ solved.rotation) - 1.0), -1.0, 1.0)
    if (np.linalg.norm(solved.position - predicted.position) > limits.max_translation_jump
            or np.degrees(np.arccos(cos)) > limits.max_rotation_jump_deg):
        return Failure.JUMP
    if cost > limits.max_cost_per_residual * max(rows, 1):
        return Failure.COST
    if (velocity_check
            and np.linalg.norm(solved.velocity - predicted.velocity) > limits.max_velocity_jump):
        return Failure.VELOCITY
    if limits.max_cost_frames > 0 and cost_excess > limits.max_cost_frames:
        return Failure.CHI2
    if blind > limits.max_blind_frames:
        return Failure.BLIND
    return None
