"""How sure a recording's offset estimate is: one standard deviation per channel that accounts
for its items' correlation.

An estimator's items (windows, frames, frame pairs) share one flight: consecutive windows
overlap, a VIO's bias states wander slowly, and every item sees the same scene and the same
motion. Their scatter divided by the square root of their count would claim a precision the
flight does not hold (over whole flights the shipped transformer's window sigmas gave z-scores
of RMS 0.18 on the gyro and 2.2 on the accelerometer). So the sampling part is measured with
**batch means**, the standard remedy for a correlated series (Flegal and Jones 2010): the
items are cut into contiguous time blocks longer than their correlation, and the spread of
the blocks' medians over the square root of their count is the median's standard error.
What every item shares (the part a model cannot see from one flight: a scene it misreads, a
motion that leaves a direction unobserved) does not average out; a method that predicts it
passes it as ``common`` (:func:`recording_sigma`). A per-method ``scale``, measured on flights
apart from those it is judged on (``experiments/calib_uncertainty.py``), makes the result a
standard deviation (z-scores of RMS 1) rather than a ranking.

Units: those of the estimate (rad/s for gyro channels, m/s^2 for accel ones).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_BLOCKS", "block_standard_error", "fit_common_scale", "fit_scale",
           "recording_sigma"]

#: Fewest blocks whose medians' spread is taken as the standard error; with fewer the items'
#: own spread is (no credit for averaging).
MIN_BLOCKS = 3


def block_standard_error(per_item, item_t_s, block_s: float) -> np.ndarray:
    """``(C,)`` the standard error of the per-channel median of ``per_item`` ``(N, C)`` (items
    at ``item_t_s`` ``(N,)`` s), by batch medians over blocks ``block_s`` seconds long.

    With fewer than :data:`MIN_BLOCKS` blocks holding items, the items' standard deviation
    (one item's error: no credit for averaging); with one item, ``inf``.
    Non-finite rows are left out.
    """
    values = np.asarray(per_item, np.float64)
    t = np.asarray(item_t_s, np.float64).reshape(-1)
    if values.ndim != 2 or t.shape != (values.shape[0],):
        raise ValueError(f"per_item must be (N, C) and item_t_s (N,), got {values.shape} and "
                         f"{t.shape}")
    if not block_s > 0.0:
        raise ValueError(f"block_s must be > 0, got {block_s}")
    keep = np.all(np.isfinite(values), axis=1) & np.isfinite(t)
    values, t = values[keep], t[keep]
    if len(values) < 2:
        return np.full(values.shape[1], np.inf)
    block = np.floor((t - t.min()) / block_s).astype(np.int64)
    ids = np.unique(block)
    if len(ids) < MIN_BLOCKS:
        return values.std(axis=0, ddof=1)
    medians = np.stack([np.median(values[block == b], axis=0) for b in ids])
    return medians.std(axis=0, ddof=1) / np.sqrt(len(ids))


def recording_sigma(per_item, item_t_s, block_s: float, *, common=None,
                    scale=1.0) -> np.ndarray:
    """``(C,)`` a recording estimate's standard deviation:
    ``scale * sqrt(block_standard_error**2 + common**2)``.

    Args:
        per_item: ``(N, C)`` the items' estimates; item_t_s: ``(N,)`` their times, s.
        block_s: the batch-means block, longer than the items' correlation (a window's
            length for overlapping windows).
        common: ``(C,)`` the error every item shares, as the method predicts it, or ``None``.
        scale: scalar or ``(C,)``, the method's measured calibration (module docstring).
    """
    se = block_standard_error(per_item, item_t_s, block_s)
    common = np.zeros_like(se) if common is None else np.asarray(common, np.float64)
    return np.asarray(scale, np.float64) * np.sqrt(np.square(se) + np.square(common))


def fit_scale(errors, sigmas) -> float:
    """The ``scale`` that makes ``errors / (scale * sigmas)`` (same shapes) have an RMS of 1
    over their finite entries: the calibration of :func:`recording_sigma`."""
    z = np.asarray(errors, np.float64) / np.asarray(sigmas, np.float64)
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise ValueError("no finite error / sigma to fit a scale on")
    return float(np.sqrt(np.mean(np.square(z))))


def fit_common_scale(errors, standard_errors, common, *, high: float = 1e3) -> float:
    """The ``k >= 0`` that makes ``errors / sqrt(standard_errors**2 + (k * common)**2)`` (same
    shapes) have an RMS of 1: how much of a model's own per-window sigma ``common`` its
    recordings share. 0 when the standard errors alone already cover the errors; ``high``
    when even that leaves them uncovered."""
    e2 = np.square(np.asarray(errors, np.float64)).reshape(-1)
    s2 = np.square(np.asarray(standard_errors, np.float64)).reshape(-1)
    c2 = np.square(np.asarray(common, np.float64)).reshape(-1)
    ok = np.isfinite(e2) & np.isfinite(s2) & np.isfinite(c2)
    e2, s2, c2 = e2[ok], s2[ok], c2[ok]
    if e2.size == 0:
        raise ValueError("no finite errors to fit on")

    def z2(k):
        return float(np.mean(e2 / np.maximum(s2 + k * k * c2, 1e-300)))

    if z2(0.0) <= 1.0:
        return 0.0
    if z2(high) > 1.0:
        return high
    lo, hi = 0.0, high
    for _ in range(200):  # z2 falls monotonically in k: bisect
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if z2(mid) > 1.0 else (lo, mid)
    return hi
