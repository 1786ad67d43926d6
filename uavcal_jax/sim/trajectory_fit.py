"""Fit a smooth :class:`~uavcal_jax.sim.trajectory.Trajectory` to recorded ground truth.

:func:`fit_tum_trajectory` fits a recorded ground truth (a TUM file or a
:class:`~uavcal_jax.data.sequence.GroundTruth`) with penalised least-squares quintic
B-splines (knots every :attr:`FitConfig.knot_spacing` seconds, a tiny third-difference
penalty that only matters where data are missing). Real motion-capture data are noisy, so
the fit smooths: it passes frequencies up to ~5 Hz with unit gain and rolls off above
~8 Hz (with the default 0.05 s knots). Instantaneous position steps in the recording
(EuRoC's Machine Hall ground truth has dozens) are removed first
(:func:`remove_position_jumps`). The file's own clock is kept: ``t_start`` / ``t_end`` are
absolute seconds of that clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy.interpolate import BSpline
from scipy.ndimage import maximum_filter1d

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError
from uavcal_jax.sim.trajectory import DEGREE, Trajectory, sign_continuous, uniform_knots

__all__ = ["FitConfig", "fit_tum_trajectory", "remove_position_jumps"]


@dataclass(frozen=True)
class FitConfig:
    """How :func:`fit_tum_trajectory` smooths recorded poses.

    Attributes:
        knot_spacing: seconds between B-spline knots (0.05 s: flat response to ~5 Hz, cut-off
            near 10 Hz). It is widened to ``min_samples_per_knot`` sample periods for sparse
            data (e.g. 20 Hz ground truth gets 0.1 s).
        smoothing: weight of the third-difference penalty on the spline coefficients,
            relative to the data term per knot interval. The default 1e-4 barely changes the
            least-squares fit (gain 0.9 at 8 Hz); it keeps the solve well posed across gaps.
        edge_padding: seconds of extra data fitted on each side of a requested
            ``start``/``duration`` window (when the source has them), so the window's ends
            are free of spline edge effects.
        min_samples_per_knot: see ``knot_spacing``.
        jump_threshold: metres; position steps larger than this (and than
            ``jump_sigmas`` robust standard deviations of the data's noise) that the
            neighbouring samples do not share are removed before fitting, see
            :func:`remove_position_jumps`. ``None`` disables it.
        jump_sigmas, jump_max_jerk: see :func:`remove_position_jumps`.
    """

    knot_spacing: float = 0.05
    smoothing: float = 1e-4
    edge_padding: float = 1.0
    min_samples_per_knot: float = 2.0
    jump_threshold: float | None = 5e-4
    jump_sigmas: float = 8.0
    jump_max_jerk: float = 100.0


def _penalised_fit(tau: np.ndarray, values: np.ndarray, knots: np.ndarray,
                   smoothing: float, order: int = 3) -> np.ndarray:
    """Coefficients of the penalised least-squares quintic spline, several columns at once."""
    B = BSpline.design_matrix(tau, knots, DEGREE).tocsr()
    m = B.shape[1]
    D = sparse.eye(m, format="csr")
    for _ in range(order):
        D = D[1:] - D[:-1]
    per_knot = len(tau) / m
    A = (B.T @ B) / per_knot + smoothing * (D.T @ D)
    rhs = (B.T @ values) / per_knot
    lu = sparse_linalg.splu(sparse.csc_matrix(A))
    return lu.solve(np.asarray(rhs))


def remove_position_jumps(t: np.ndarray, position: np.ndarray, threshold: float = 5e-4,
                          sigmas: float = 8.0, max_jerk: float = 100.0,
                          max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Remove step discontinuities from recorded positions.

    Some ground truths have instantaneous position jumps that the body cannot have made
    (EuRoC's Machine Hall sequences: dozens of 1-130 mm steps between two 200 Hz samples,
    with the velocity continuous across them). Left in, each one is a huge acceleration
    spike in the synthetic IMU. A step at sample ``i`` is found from the residual of the
    velocity ``v_i = (p_{i+1} - p_i) / dt_i`` against the mean of its neighbours
    ``(v_{i-2} + v_{i+2}) / 2`` (zero to second order for smooth motion); the largest
    local residuals above ``max(threshold, sigmas * robust noise std, 2 max_jerk dt^3)`` (the
    last term is what real motion with that jerk leaves in the residual; it only matters for
    sparse data: 25 mm at 20 Hz with the default 100 m/s^3) are taken as jumps,
    every later sample is shifted back by the jump, and this repeats until none remain. The
    result is re-centred so the mean correction is zero. An isolated outlier sample shows
    up as two opposite jumps and is repaired the same way.

    Args:
        t: (N,) seconds, increasing.
        position: (N, 3).
        threshold: metres, the smallest step treated as a jump.
        sigmas: how many robust standard deviations of the residuals a jump must exceed.
        max_jerk: m/s^3, the largest jerk expected of the real motion.

    Returns:
        ``(corrected (N, 3), jumps (J,) indices i of the steps p_i -> p_{i+1})``.
    """
    p = np.array(position, dtype=np.float64, copy=True)
    t = np.asarray(t, dtype=np.float64)
    n = len(p)
    if n < 7:
        return p, np.zeros(0, dtype=np.int64)
    dt = np.diff(t)[:, None]
    found: list[np.ndarray] = []
    correction = np.zeros_like(p)
    limit = None
    for _ in range(max_iterations):
        v = np.diff(p, axis=0) / dt
        # residual of step s = 2 .. n-4 against its neighbours two steps away (an outlier
        # sample spoils two adjacent steps; these predictions skip both)
        resid = (v[2:-2] - 0.5 * (v[:-4] + v[4:])) * dt[2:-2]
        r = np.linalg.norm(resid, axis=1)
        if limit is None:
            mad = np.median(np.abs(resid - np.median(resid, axis=0)), axis=0)
            limit = max(threshold, sigmas * 1.4826 * float(np.linalg.norm(mad)),
                        2.0 * max_jerk * float(np.median(dt)) ** 3)
        local_max = maximum_filter1d(r, size=5, mode="constant", cval=0.0) <= r
        idx = np.flatnonzero(local_max & (r > limit))
        if idx.size == 0:
            break
        steps = np.zeros_like(p)
        steps[idx + 3] = resid[idx]  # resid[j] is the step from sample j+2 to j+3
        shift = np.cumsum(steps, axis=0)
        p -= shift
        correction += shift
        found.append(idx + 2)
    p += correction.mean(axis=0)
    jumps = np.unique(np.concatenate(found)) if found else np.zeros(0, dtype=np.int64)
    return p, jumps


def _load_ground_truth(source) -> tuple[GroundTruth, str]:
    if isinstance(source, GroundTruth):
        return source, "ground-truth"
    path = Path(source)
    return read_tum(path), path.stem


def fit_tum_trajectory(source: str | Path | GroundTruth, start: float | None = None,
                       duration: float | None = None,
                       config: FitConfig = FitConfig()) -> Trajectory:  # noqa: B008
    """Fit a smooth trajectory to recorded poses (TUM file or ``GroundTruth``).

    Position: one penalised least-squares quintic B-spline per axis (uniform knots). Rotation:
    the quaternions are made sign-continuous, each component is fitted the same way, and the
    result is normalised on evaluation (angular velocity from the unnormalised spline).

    Args:
        source: a TUM file (``t tx ty tz qx qy qz qw``, read with
            :func:`uavcal_jax.data.tum.read_tum`) or a ``GroundTruth`` (its position and
            quaternion; other fields are ignored).
        start: first time of the trajectory, absolute seconds of the source's clock
            (default: the first pose). Clipped to the data.
        duration: seconds (default: to the last pose). Clipped to the data.
        config: smoothing settings.

    Returns:
        A :class:`Trajectory` with ``t_start``/``t_end`` in the source's own clock.

    Raises:
        DataError: too few poses, or a window that does not overlap the data.
    """
    gt, name = _load_ground_truth(source)
    where = None if isinstance(source, GroundTruth) else Path(source)
    t_ns = np.asarray(gt.t_ns, dtype=np.int64)
    pos = np.asarray(gt.position, dtype=np.float64)
    quat = np.asarray(gt.quaternion, dtype=np.float64)
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"need at least {2 * (DEGREE + 1)} poses to fit a trajectory, "
                        f"got {len(t_ns)}", where)
    if np.any(np.diff(t_ns) <= 0):
        raise DataError("pose timestamps are not strictly increasing", where)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise DataError("non-finite poses", where)

    t_first, t_last = t_ns[0] * 1e-9, t_ns[-1] * 1e-9
    w0 = t_first if start is None else max(float(start), t_first)
    w1 = t_last if duration is None else min(w0 + float(duration), t_last)
    if start is not None and float(start) > t_last:
        raise DataError(f"start {start} s is after the last pose ({t_last:.6f} s)", where)
    if w1 - w0 <= 0:
        raise DataError(f"empty window [{w0}, {w1}] s", where)

    t = t_ns * 1e-9
    keep = (t >= w0 - config.edge_padding) & (t <= w1 + config.edge_padding)
    t_ns, pos, quat = t_ns[keep], pos[keep], quat[keep]
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"only {len(t_ns)} poses in the window [{w0}, {w1}] s", where)
    quat = sign_continuous(quat / np.linalg.norm(quat, axis=1, keepdims=True))

    t_ref_ns = int(t_ns[0])
    tau = (t_ns - t_ref_ns).astype(np.float64) * 1e-9
    if config.jump_threshold is not None:
        pos, _ = remove_position_jumps(tau, pos, config.jump_threshold, config.jump_sigmas,
                                       config.jump_max_jerk)
    period = float(np.median(np.diff(tau)))
    spacing = max(config.knot_spacing, config.min_samples_per_knot * period)
    knots = uniform_knots(tau[0], tau[-1], spacing)
    coef = _penalised_fit(tau, np.concatenate([pos, quat], axis=1), knots, config.smoothing)
    pos_spline = BSpline(knots, coef[:, :3], DEGREE)
    quat_spline = BSpline(knots, coef[:, 3:], DEGREE)
    return Trajectory(float(w0), float(w1), pos_spline, quat_spline, t_ref_ns, name)
