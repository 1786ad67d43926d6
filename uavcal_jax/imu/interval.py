"""Cut an interval ``[t_start, t_end]`` out of a timestamped IMU stream for :func:`preintegrate`.

The stream's samples ``t_0 < t_1 < ...`` are read as a zero-order hold (sample ``k`` holds
on ``[t_k, t_{k+1})``, GTSAM's ``integrateMeasurement(acc, gyro, t_{k+1} - t_k)``), except at
the interval's start: when ``t_start`` falls between two samples the first segment holds the
**linear interpolation** of the two samples at ``t_start``. The segments are::

    [t_start, t_{k+1}), [t_{k+1}, t_{k+2}), ..., [t_m, t_end)

(``t_k <= t_start < t_{k+1}``, ``t_m`` the last sample before ``t_end``), so the durations sum
to exactly ``t_end - t_start`` and an interval whose ends are sample times gives the plain
GTSAM loop. Intervals must lie inside the stream: ``t_0 <= t_start < t_end <= t_last``.

Times may be int64 nanoseconds (EuRoC; durations are then computed exactly in integers and
converted to seconds) or float seconds. The functions validate eagerly.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from uavcal_jax.errors import DataError

__all__ = [
    "ImuInterval",
    "interval_samples",
    "interval_batch",
    "interval_capacity",
]


@dataclasses.dataclass(frozen=True)
class ImuInterval:
    """Samples of one or more intervals, ready for :func:`~uavcal_jax.imu.preintegrate`.

    Attributes:
        dt: (..., N) seconds each segment lasts (0 on padding).
        gyro: (..., N, 3) rad/s.
        accel: (..., N, 3) m/s^2.
        mask: (..., N) bool, ``True`` on real segments.
        complete: (...) bool, ``False`` when the capacity cut the interval short (padded form).
    """

    dt: np.ndarray | jax.Array
    gyro: np.ndarray | jax.Array
    accel: np.ndarray | jax.Array
    mask: np.ndarray | jax.Array
    complete: np.ndarray | jax.Array


jax.tree_util.register_dataclass(
    ImuInterval, data_fields=["dt", "gyro", "accel", "mask", "complete"], meta_fields=[]
)


def _unpack_stream(t, gyro, accel):
    if gyro is None and accel is None and hasattr(t, "t_ns"):
        return np.asarray(t.t_ns), np.asarray(t.gyro, float), np.asarray(t.accel, float)
    return np.asarray(t), np.asarray(gyro, float), np.asarray(accel, float)


def _validate_stream(t, gyro, accel):
    if t.ndim != 1 or gyro.shape != (t.shape[0], 3) or accel.shape != (t.shape[0], 3):
        raise DataError(
            f"IMU stream shapes must be t (N,), gyro (N, 3), accel (N, 3); got {t.shape}, "
            f"{gyro.shape}, {accel.shape}"
        )
    if t.shape[0] < 2:
        raise DataError("IMU stream needs at least 2 samples")
    if np.issubdtype(t.dtype, np.floating) and not np.all(np.isfinite(t)):
        raise DataError("IMU timestamps contain NaN or inf")
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(
            f"IMU timestamps must increase strictly (sample {k + 1}: {t[k + 1]} after {t[k]})"
        )


def interval_samples(t, gyro=None, accel=None, t_start=None, t_end=None) -> ImuInterval:
    """Segments of ``[t_start, t_end]`` (see the module docstring), exactly sized, NumPy.

    Args:
        t: (N,) int64 nanoseconds or float seconds -- or an ``ImuData`` (then ``gyro`` and
            ``accel`` are omitted and ``t_start``, ``t_end`` are nanoseconds).
        gyro, accel: (N, 3).
        t_start, t_end: interval ends, in the unit of ``t``.

    Raises:
        DataError: bad stream, ``t_end <= t_start``, an end outside the stream, or
            non-finite samples inside the interval.
    """
    t, gyro, accel = _unpack_stream(t, gyro, accel)
    _validate_stream(t, gyro, accel)
    integer = np.issubdtype(t.dtype, np.integer)
    if integer:
        ts, te = int(t_start), int(t_end)
    else:
        ts, te = float(t_start), float(t_end)
        if not (np.isfinite(ts) and np.isfinite(te)):
            raise DataError(f"interval ends must be finite, got [{t_start}, {t_end}]")
    if not te > ts:
        raise DataError(f"empty interval: t_end ({t_end}) <= t_start ({t_start})")
    if ts < t[0] or te > t[-1]:
        raise DataError(
            f"interval [{t_start}, {t_end}] is not inside the IMU stream [{t[0]}, {t[-1]}]"
        )
    k = int(np.searchsorted(t, ts, side="right")) - 1  # t[k] <= ts < t[k+1]
    m = int(np.searchsorted(t, te, side="left"))  # first sample >= te
    inner = np.arange(k + 1, m)  # samples strictly inside (ts, te)
    knots = np.concatenate([[ts], t[inner], [te]])
    if integer:
        dt = np.diff(knots.astype(np.int64)).astype(np.float64) * 1e-9
    else:
        dt = np.diff(knots.astype(np.float64))
    # Linear interpolation at t_start between samples k and k+1 (k + 1 exists: ts < te <= t[-1]).
    if integer:
        frac = float(ts - int(t[k])) / float(int(t[k + 1]) - int(t[k]))
    else:
        frac = (ts - t[k]) / (t[k + 1] - t[k])
    g0 = gyro[k] + frac * (gyro[k + 1] - gyro[k])
    a0 = accel[k] + frac * (accel[k + 1] - accel[k])
    g = np.concatenate([g0[None], gyro[inner]], axis=0)
    a = np.concatenate([a0[None], accel[inner]], axis=0)
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
        raise DataError(f"non-finite IMU samples inside the interval [{t_start}, {t_end}]")
    return ImuInterval(dt=dt, gyro=g, accel=a, mask=np.ones(dt.shape, bool),
                       complete=np.asarray(True))


def interval_capacity(t, starts, ends) -> int:
    """Smallest capacity that holds every interval ``[starts[i], ends[i]]`` of stream ``t``."""
    t = np.asarray(getattr(t, "t_ns", t))
    k = np.searchsorted(t, np.asarray(starts), side="right") - 1
    m = np.searchsorted(t, np.asarray(ends), side="left")
    return int(np.max(m - k)) if np.size(k) else 1


def interval_batch(t, gyro=None, accel=None, starts=None, ends=None, capacity: int | None = None
                   ) -> ImuInterval:
    """Many intervals, padded to one capacity (NumPy): fields shaped (M, capacity[, 3]).

    ``capacity`` defaults to :func:`interval_capacity`; a smaller one raises. Feed the result
    to ``jax.vmap(preintegrate)`` or straight to :func:`preintegrate` (leading batch axis)
    with ``mask=batch.mask``.
    """
    t, gyro, accel = _unpack_stream(t, gyro, accel)
    starts = np.atleast_1d(np.asarray(starts))
    ends = np.atleast_1d(np.asarray(ends))
    if starts.shape != ends.shape or starts.ndim != 1:
        raise DataError(
            f"starts and ends must be equal-length 1-D, got {starts.shape}, {ends.shape}"
        )
    need = interval_capacity(t, starts, ends) if len(starts) else 1
    capacity = need if capacity is None else int(capacity)
    if capacity < need:
        raise DataError(f"capacity {capacity} is too small for these intervals (need {need})")
    M = len(starts)
    dt = np.zeros((M, capacity))
    g = np.zeros((M, capacity, 3))
    a = np.zeros((M, capacity, 3))
    mask = np.zeros((M, capacity), bool)
    for i in range(M):
        iv = interval_samples(t, gyro, accel, starts[i], ends[i])
        n = iv.dt.shape[0]
        dt[i, :n], g[i, :n], a[i, :n], mask[i, :n] = iv.dt, iv.gyro, iv.accel, True
    return ImuInterval(dt=dt, gyro=g, accel=a, mask=mask, complete=np.ones(M, bool))
