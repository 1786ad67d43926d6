"""Failure detection after a window solve (VINS-Fusion's ``failureDetection``, which it ships
disabled; here it runs): a pure function of the solved newest frame, its IMU prediction, the
solve's cost, the landmark count and the share of the newest frame's tracked observations
that the solve rejected as outliers, returning a typed :class:`Failure` or ``None`` when the
window is healthy. The limits are :class:`~uavcal_jax.vio.config.FailureLimits`.

The outlier test (:func:`rejected_observations`, :func:`outlier_frames`) is the one that sees
wrong tracks: the robust kernel and the post-solve prune (observations off by more than 3 px
leave the window) keep a window whose newest frames' tracks are garbage close to its IMU
prediction, so neither the velocity nor the jump test fires while the window runs on the IMU
alone. On a simulated V1_02 flight (376x240, 1.5 m/s) with 1 s of track ids shuffled between
frames the newest frame's rejected share rose from 0.02-0.07 to 0.98-1.0 at once; without
this test nothing was flagged and the error grew from 0.015 to 0.16 m.

:class:`FailureCounters` carries the tests' counts of consecutive frames from one frame to
the next (the estimator starts a new one with each new window).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import FailureLimits

__all__ = ["Failure", "FailureCounters", "blind_frames", "check_failure", "chi2_bound",
           "cost_excess_frames", "outlier_frames", "rejected_observations"]


class Failure(enum.Enum):
    """Why the window failed; the value is the estimate's ``reason``."""

    NAN = "nan"  # a non-finite state or cost
    BIAS = "bias"  # a bias estimate beyond its sane norm
    JUMP = "jump"  # the solved frame far from its IMU prediction
    COST = "cost"  # the cost per residual row blew up
    VELOCITY = "velocity"  # the solved velocity far from its IMU prediction
    CHI2 = "chi2"  # the normalised window cost above its chi-square bound for several frames
    OUTLIERS = "outliers"  # most of the newest frames' tracked observations rejected
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


def rejected_observations(updates: tuple, observation_used: np.ndarray) -> tuple[int, int]:
    """``(tracked, rejected)``: the newest frame's observations of landmarks anchored in an
    earlier keyframe (its tracks; the stereo observations of the landmarks it starts cannot be
    wrong against an earlier frame), and how many of them the solve's prune removed (off by
    more than its ``max_error_px``, or their landmark left for its depth).

    Args:
        updates: the frame's padded window updates
            (:meth:`~uavcal_jax.vio.slots.WindowSlots.measurements`: landmark slots, bearings,
            inverse depths, observation slots, their landmarks, cameras, coordinates; padding
            at the capacities ``L`` and ``M``).
        observation_used: (M,) bool, the window's observation slots in use after the prune.
    """
    lm_slot, o_slot, o_lm = updates[0], updates[3], updates[4]
    used = np.asarray(observation_used, bool)
    # the landmarks started here; their padding (slot L) is no landmark an observation names
    tracked = (o_slot < len(used)) & ~np.isin(o_lm, lm_slot)
    return int(tracked.sum()), int(np.sum(~used[o_slot[tracked]]))


def outlier_frames(previous: int, tracked: int, rejected: int, limits: FailureLimits) -> int:
    """Consecutive frames, this one included (``previous`` the count before it), with at least
    ``limits.min_outlier_tracks`` tracked observations of which more than
    ``limits.max_outlier_share`` were rejected (:func:`rejected_observations`). A frame with
    fewer tracked observations leaves the count as it is (too few to judge; the blind test
    covers a frame with none)."""
    if tracked < limits.min_outlier_tracks:
        return previous
    return previous + 1 if rejected > limits.max_outlier_share * tracked else 0


def check_failure(solved: BodyState, predicted: BodyState, cost: float, rows: int, blind: int,
                  limits: FailureLimits, cost_excess: int = 0, velocity_check: bool = True,
                  outliers: int = 0) -> Failure | None:
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
        outliers: :func:`outlier_frames` after this frame; more than
            ``limits.max_outlier_frames`` fail (0 of them: the test is off).
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
    if limits.max_outlier_frames > 0 and outliers > limits.max_outlier_frames:
        return Failure.OUTLIERS
    if blind > limits.max_blind_frames:
        return Failure.BLIND
    return None


@dataclasses.dataclass
class FailureCounters:
    """One window's counts of consecutive failing frames (:func:`blind_frames`,
    :func:`cost_excess_frames`, :func:`outlier_frames`), updated by :meth:`check` after each
    solve."""

    blind: int = 0
    cost_excess: int = 0
    outliers: int = 0

    def check(self, solved: BodyState, predicted: BodyState, cost: float, rows: int,
              active_landmarks: int, updates: tuple, observation_used: np.ndarray,
              limits: FailureLimits, settled: bool) -> Failure | None:
        """Count this frame, then :func:`check_failure`.

        Args:
            solved, predicted, cost, rows, limits: as :func:`check_failure`.
            active_landmarks: landmarks observed in the window after the solve.
            updates, observation_used: as :func:`rejected_observations`.
            settled: the window's start is no longer an assumption (its start check ended):
                the velocity and outlier tests run (an at-rest start on a body in flight is
                corrected by its first solves, or re-opened by the check, which is no
                failure, though until then most tracks look wrong against it: a simulated
                outdoor flight at 8 m/s had 55-98 % rejected in its first 9 frames).
        """
        self.blind = blind_frames(self.blind, active_landmarks, limits)
        self.cost_excess = cost_excess_frames(self.cost_excess, cost, rows, limits)
        if settled:
            self.outliers = outlier_frames(
                self.outliers, *rejected_observations(updates, observation_used), limits)
        return check_failure(solved, predicted, cost, rows, self.blind, limits,
                             self.cost_excess, velocity_check=settled, outliers=self.outliers)
