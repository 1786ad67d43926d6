"""Recorded poses as they come: sample periods, near-duplicate stamps, time weights, the
noise of positions and orientations, and position steps.

:mod:`uavcal_jax.sim.trajectory_fit` prepares a recording with these before fitting a spline
through it (its module docstring gives the order and the reasons). All inputs are seconds
``t (N,)`` increasing, positions ``(N, 3)`` metres, quaternions ``(N, 4)`` (w, x, y, z).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import maximum_filter1d

__all__ = ["drop_inconsistent_duplicates", "merge_near_duplicates", "remove_position_jumps",
           "rotation_noise", "sample_noise", "step_ramps", "time_weights", "typical_period"]

#: Peak acceleration of the smooth ramp :func:`remove_position_jumps` puts in place of a step
#: (m/s^2): below the white noise of one 200 Hz sample of EuRoC's IMU (0.028 m/s^2).
RAMP_ACCELERATION = 0.02

#: Peak second derivative of the quintic smooth step ``10 x^3 - 15 x^4 + 6 x^5`` on [0, 1].
_SMOOTHSTEP_PEAK_ACCEL = 10.0 / math.sqrt(3.0)

#: Normal-consistent scale of the median absolute deviation.
_MAD_SCALE = 1.4826


def typical_period(t: np.ndarray) -> float:
    """Median sample interval of (N,) seconds ``t``, ignoring intervals under 1 % of the mean
    (near-duplicate stamps, however many) so that it is the period of the stream."""
    dt = np.diff(np.asarray(t, dtype=np.float64))
    if dt.size == 0:
        return 0.0
    regular = dt[dt > 0.01 * (t[-1] - t[0]) / len(dt)]
    return float(np.median(regular if regular.size else dt))


def merge_near_duplicates(t_ns: np.ndarray, position: np.ndarray, quaternion: np.ndarray,
                          min_dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Merge runs of poses whose consecutive stamps are closer than ``min_dt`` seconds.

    Each run becomes one pose at its mean time (int64 ns), with the mean position and the
    normalised mean quaternion (``quaternion`` must be sign-continuous, (w, x, y, z)).

    Returns:
        ``(t_ns (M,), position (M, 3), quaternion (M, 4), merged)`` with ``merged = N - M``.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    close = np.diff(t_ns) * 1e-9 < min_dt
    if not np.any(close):
        return t_ns, position, quaternion, 0
    group = np.concatenate([[0], np.cumsum(~close)])
    count = np.bincount(group).astype(np.float64)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(group, weights=col) for col in values.T], axis=1) \
            / count[:, None]

    first = t_ns[np.concatenate([[True], ~close])]
    offset = np.bincount(group, weights=(t_ns - first[group]).astype(np.float64)) / count
    t_merged = first + np.round(offset).astype(np.int64)
    q = mean(quaternion)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return t_merged, mean(position), q, int(len(t_ns) - len(t_merged))


def drop_inconsistent_duplicates(t_ns: np.ndarray, position: np.ndarray, min_dt: float,
                                 floor: float, sigmas: float = 5.0) -> np.ndarray:
    """Which poses to keep of runs whose consecutive stamps are closer than ``min_dt`` seconds.

    Two poses a fraction of a millisecond apart can only differ by the noise and the motion in
    that fraction; motion-capture exports also have pairs that differ by centimetres, where a
    pose was stamped a sample period or more from when it was taken (timestamp jitter).
    Averaged, such a pair is an outlier of half that difference; read as a position step it
    shifts the flight. So each run is compared with the straight line between the nearest
    poses that have no near-duplicate (before and after): the member closest to it is kept,
    with the members within ``max(floor, sigmas * sqrt(2) * noise) + speed * |dt|`` of it
    (``noise``: the 3-D magnitude of :func:`sample_noise` on those unpaired poses; ``speed``:
    the line's); the others are dropped. The kept members are then merged
    (:func:`merge_near_duplicates`). With fewer than 5 unpaired poses nothing is dropped.

    Args:
        t_ns: (N,) int64 nanoseconds, increasing.
        position: (N, 3) metres.
        min_dt: seconds.
        floor: metres; members closer than this are never dropped.
        sigmas: how many noise standard deviations two members may differ by.

    Returns:
        (N,) bool, ``True`` for the poses to keep.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    p = np.asarray(position, dtype=np.float64)
    keep = np.ones(len(t_ns), dtype=bool)
    close = np.diff(t_ns) * 1e-9 < min_dt
    paired = np.zeros(len(t_ns), dtype=bool)
    paired[:-1] |= close
    paired[1:] |= close
    single = np.flatnonzero(~paired)
    if not np.any(close) or single.size < 5:
        return keep
    t = (t_ns - t_ns[0]) * 1e-9
    ts, ps = t[single], p[single]
    tolerance = max(floor, sigmas * math.sqrt(2.0) * float(np.linalg.norm(sample_noise(ts, ps))))
    # the straight line between the unpaired poses around each pose, and its speed
    right = np.clip(np.searchsorted(ts, t), 1, single.size - 1)
    left = right - 1
    frac = ((t - ts[left]) / (ts[right] - ts[left]))[:, None]
    line = ps[left] + frac * (ps[right] - ps[left])
    speed = np.linalg.norm(ps[right] - ps[left], axis=1) / (ts[right] - ts[left])
    starts = np.flatnonzero(np.concatenate([[True], ~close]))
    ends = np.concatenate([starts[1:], [len(t_ns)]])
    for a, b in zip(starts[ends - starts > 1], ends[ends - starts > 1], strict=True):
        best = a + int(np.argmin(np.linalg.norm(p[a:b] - line[a:b], axis=1)))
        allowed = tolerance + speed[best] * np.abs(t[a:b] - t[best])
        keep[a:b] = np.linalg.norm(p[a:b] - p[best], axis=1) <= allowed
    return keep


def time_weights(t: np.ndarray, period: float) -> np.ndarray:
    """(N,) weight of each sample: the time it stands for (half the span to its neighbours;
    the one neighbour at the ends) in units of ``period``, at most 1. Regular sampling gets
    1 everywhere; a burst shares the weight of the time it covers; a sample beside a gap
    counts as one."""
    t = np.asarray(t, dtype=np.float64)
    dt = np.diff(t)
    span = np.concatenate([dt[:1], 0.5 * (dt[:-1] + dt[1:]), dt[-1:]])
    return np.minimum(span / period, 1.0)


def _cubic_stencils(t: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange weights ``(N-4, 4)`` of the cubic through samples ``i-2, i-1, i+1, i+2``
    evaluated at ``t_i`` (``i = 2 .. N-3``), and which of these stencils to use: those no wider
    than eight periods (no gap inside), when at least 20 are; all otherwise."""
    centre = t[2:-2]
    nodes = np.stack([t[:-4], t[1:-3], t[3:-1], t[4:]], axis=1)
    weights = np.ones_like(nodes)
    for j in range(4):
        for k in range(4):
            if k != j:
                weights[:, j] *= (centre - nodes[:, k]) / (nodes[:, j] - nodes[:, k])
    narrow = nodes[:, 3] - nodes[:, 0] <= 8.0 * period
    return weights, (narrow if np.count_nonzero(narrow) >= 20 else np.ones_like(narrow))


def _robust_std(z: np.ndarray, clip: float = 3.5) -> np.ndarray:
    """Per-column standard deviation of (N, C) ``z``, robustly: the RMS of the values within
    ``clip`` median-absolute-deviation standard deviations of the median (outliers and the
    odd stencil across a gap left out), corrected for the Gaussian tails cut off. On 500
    Gaussian samples its relative error is ~3 %, the median absolute deviation's ~5 %: the
    discrepancy principle needs the former."""
    centred = z - np.median(z, axis=0)
    mad = _MAD_SCALE * np.median(np.abs(centred), axis=0)
    inside = np.abs(centred) <= clip * mad
    # E[x^2 | |x| <= c] / sigma^2 for a Gaussian
    kept = 1.0 - 2.0 * clip * math.exp(-0.5 * clip**2) / math.sqrt(2.0 * math.pi) \
        / math.erf(clip / math.sqrt(2.0))
    ms = np.sum(np.where(inside, centred**2, 0.0), axis=0) / np.maximum(inside.sum(axis=0), 1)
    return np.sqrt(ms / kept)


def sample_noise(t: np.ndarray, values: np.ndarray, period: float | None = None) -> np.ndarray:
    """Robust per-column noise standard deviation of samples of a smooth signal.

    Each sample ``i`` is compared with the cubic through its neighbours ``i-2, i-1, i+1, i+2``
    (Lagrange weights ``L`` for its irregular times; for smooth motion the difference is the
    noise up to the fourth derivative times the sample interval to the fourth). The
    difference is divided by ``sqrt(1 + sum L^2)`` (its standard deviation in units of the
    noise's) and its robust spread (RMS within 3.5 median-absolute-deviation standard
    deviations) is the noise's standard deviation. Stencils wider than eight periods (gaps)
    are left out when enough others remain.

    Args:
        t: (N,) seconds, increasing, N >= 5 (near-duplicates merged: see
            :func:`merge_near_duplicates`).
        values: (N, C).
        period: the typical interval (default :func:`typical_period`).

    Returns:
        (C,) standard deviations, in ``values``' units.
    """
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64).reshape(len(t), -1)
    if len(t) < 5:
        return np.zeros(y.shape[1])
    weights, use = _cubic_stencils(t, typical_period(t) if period is None else period)
    neighbours = np.stack([y[:-4], y[1:-3], y[3:-1], y[4:]], axis=1)  # (N-4, 4, C)
    diff = y[2:-2] - np.einsum("nj,njc->nc", weights, neighbours)
    z = diff / np.sqrt(1.0 + np.sum(weights**2, axis=1))[:, None]
    return _robust_std(z[use])


def rotation_noise(t: np.ndarray, quaternion: np.ndarray,
                   period: float | None = None) -> np.ndarray:
    """Robust per-axis noise standard deviation (radians, body axes) of orientation samples.

    As :func:`sample_noise`, with the cubic's prediction ``q_hat`` (normalised) compared to
    ``q_i`` as a small rotation ``2 Im(conj(q_hat) q_i)`` in the body frame: unlike the
    quaternion's components, whose share of the noise turns with the orientation, these
    three axes keep theirs, so a per-axis robust spread is a fair measure.

    Args:
        t: (N,) seconds, increasing.
        quaternion: (N, 4) unit (w, x, y, z), sign-continuous.
        period: the typical interval (default :func:`typical_period`).

    Returns:
        (3,) standard deviations, radians.
    """
    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(quaternion, dtype=np.float64)
    if len(t) < 5:
        return np.zeros(3)
    weights, use = _cubic_stencils(t, typical_period(t) if period is None else period)
    neighbours = np.stack([q[:-4], q[1:-3], q[3:-1], q[4:]], axis=1)
    q_hat = np.einsum("nj,njc->nc", weights, neighbours)
    q_hat /= np.linalg.norm(q_hat, axis=1, keepdims=True)
    q_i = q[2:-2]
    # Im(conj(a) b) for (w, x, y, z) quaternions
    im = (q_hat[:, :1] * q_i[:, 1:] - q_i[:, :1] * q_hat[:, 1:]
          - np.cross(q_hat[:, 1:], q_i[:, 1:]))
    z = 2.0 * im / np.sqrt(1.0 + np.sum(weights**2, axis=1))[:, None]
    return _robust_std(z[use])


def _smooth_step(x: np.ndarray) -> np.ndarray:
    """Quintic smooth step: 0 for ``x <= 0``, 1 for ``x >= 1``, ``10 x^3 - 15 x^4 + 6 x^5``
    between (continuous up to the second derivative)."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10.0 + x * (-15.0 + 6.0 * x))


def step_ramps(t: np.ndarray, t_step: np.ndarray, size: np.ndarray,
               ramp_acceleration: float = RAMP_ACCELERATION,
               min_width: np.ndarray | float = 0.0) -> np.ndarray:
    """(N, 3) correction that turns position steps into smooth ramps of the same size.

    A step ``d`` (metres, (3,)) at ``t_step`` is ``d H(t - t_step)``; this returns, summed over
    the steps, ``d (H(t - t_step) - S((t - t_step) / T + 1/2))`` with ``S`` the quintic
    smooth step and ``T = max(min_width, sqrt(5.77 |d| / ramp_acceleration))`` (the ramp's
    peak acceleration is ``ramp_acceleration``): subtracted from the positions, it replaces
    each step by a ramp centred on it, and it is zero outside ``t_step +- T / 2``.

    Args:
        t: (N,) seconds, increasing.
        t_step: (J,) seconds.
        size: (J, 3) metres.
        ramp_acceleration: m/s^2.
        min_width: seconds, scalar or (J,).
    """
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros((len(t), 3))
    size = np.asarray(size, dtype=np.float64).reshape(-1, 3)
    width = np.maximum(min_width, np.sqrt(_SMOOTHSTEP_PEAK_ACCEL
                                          * np.linalg.norm(size, axis=1) / ramp_acceleration))
    for tj, d, w in zip(np.asarray(t_step, dtype=np.float64), size, width, strict=True):
        a, b = np.searchsorted(t, [tj - 0.5 * w, tj + 0.5 * w])
        x = (t[a:b] - tj) / w + 0.5
        out[a:b] += d * ((t[a:b] > tj).astype(np.float64) - _smooth_step(x))[:, None]
    return out


def remove_position_jumps(t: np.ndarray, position: np.ndarray, threshold: float = 5e-4,
                          sigmas: float = 8.0, max_jerk: float = 100.0,
                          ramp_acceleration: float = RAMP_ACCELERATION,
                          max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Remove step discontinuities from recorded positions.

    Some ground truths have instantaneous position jumps that the body cannot have made
    (EuRoC's Machine Hall sequences: dozens of 1-130 mm steps between two 200 Hz samples,
    with the velocity continuous across them). Left in, each one is a huge acceleration
    spike in the synthetic IMU. A step at sample ``i`` is found from the residual of the
    velocity ``v_i = (p_{i+1} - p_i) / dt_i`` against the velocity interpolated (linearly in
    time, between the steps' midpoints) from the steps two away on each side, ``v_{i-2}``
    and ``v_{i+2}``, times ``dt_i``: zero to second order for smooth motion. Residuals above
    ``limit_i = max(threshold, sigmas * robust noise std * k_i, max_jerk * e_i)`` that are
    the largest (relative to their limits) within two steps are taken as jumps, each is
    replaced by a smooth ramp of the same size centred on it (:func:`step_ramps`: its peak
    acceleration is ``ramp_acceleration``, below the IMU's noise), and this repeats until
    none remain. The corrected positions equal the recorded ones outside the ramps: a
    repair cannot move the rest of the flight away from the file (shifting every later
    sample back by the jump, as this once did, added the jumps up: centimetres over a
    EuRoC Machine Hall flight, and a drifting offset wherever noise made a step's two
    halves differ). ``k_i`` is the
    residual's noise in units of its noise for regular sampling (1 there; large where a
    neighbouring step is short, as beside a near-duplicate stamp, whose noisy velocity would
    otherwise look like a jump); ``e_i`` is the residual that motion with unit jerk can leave
    (``2 dt^3`` for regular sampling; it only matters for sparse data or across gaps: 25 mm
    at 20 Hz with the default 100 m/s^3). For regular sampling the limit is the same for
    every step. An isolated outlier sample shows up as two opposite jumps whose ramps
    (nearly) cancel: it is moved onto its neighbours.

    Args:
        t: (N,) seconds, increasing.
        position: (N, 3).
        threshold: metres, the smallest step treated as a jump.
        sigmas: how many robust standard deviations of the residuals a jump must exceed.
        max_jerk: m/s^3, the largest jerk expected of the real motion.
        ramp_acceleration: m/s^2, see :func:`step_ramps`.

    Returns:
        ``(corrected (N, 3), jumps (J,) indices i of the steps p_i -> p_{i+1})``.
    """
    p = np.array(position, dtype=np.float64, copy=True)
    t = np.asarray(t, dtype=np.float64)
    n = len(p)
    if n < 7:
        return p, np.zeros(0, dtype=np.int64)
    dt = np.diff(t)
    mid = 0.5 * (t[:-1] + t[1:])
    # step s = 2 .. n-4 against its neighbours two steps away (an outlier sample spoils two
    # adjacent steps; these predictions skip both), interpolated to its midpoint
    d_s, before, after = dt[2:-2], mid[2:-2] - mid[:-4], mid[4:] - mid[2:-2]
    w_prev, w_next = after / (before + after), before / (before + after)
    # noise of the residual relative to regular sampling's (steps s-2, s, s+2 share no
    # samples, so their noises add)
    k = np.sqrt((1.0 + (d_s * w_prev / dt[:-4]) ** 2 + (d_s * w_next / dt[4:]) ** 2) / 1.5)
    # what smooth motion of unit jerk leaves: the interpolation error of the velocity, and
    # the difference between a step's mean velocity and its midpoint value
    jerk_error = d_s * (0.5 * before * after
                        + np.abs(d_s**2 - w_prev * dt[:-4] ** 2 - w_next * dt[4:] ** 2) / 24.0)
    found: list[np.ndarray] = []
    limit = None
    for _ in range(max_iterations):
        v = np.diff(p, axis=0) / dt[:, None]
        resid = (v[2:-2] - (w_prev[:, None] * v[:-4] + w_next[:, None] * v[4:])) * d_s[:, None]
        r = np.linalg.norm(resid, axis=1)
        if limit is None:
            z = resid / k[:, None]
            mad = np.median(np.abs(z - np.median(z, axis=0)), axis=0)
            noise = _MAD_SCALE * float(np.linalg.norm(mad))
            limit = np.maximum(np.maximum(threshold, sigmas * noise * k), max_jerk * jerk_error)
        # local maxima of the residual against its limit (for regular sampling the limit is
        # the same everywhere; beside a near-duplicate stamp it is huge, and the residual
        # there must not hide a jump two steps away)
        score = r / limit
        local_max = maximum_filter1d(score, size=5, mode="constant", cval=0.0) <= score
        idx = np.flatnonzero(local_max & (score > 1.0))
        if idx.size == 0:
            break
        # resid[j] is the step from sample j+2 to j+3; the ramp spans at least 8 intervals
        p -= step_ramps(t, mid[idx + 2], resid[idx], ramp_acceleration, 8.0 * d_s[idx])
        found.append(idx + 2)
    jumps = np.unique(np.concatenate(found)) if found else np.zeros(0, dtype=np.int64)
    return p, jumps


# --------------------------------------------------------------------------------------------
# The penalised fit
# --------------------------------------------------------------------------------------------
