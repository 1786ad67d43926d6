"""Timestamp checks shared by the readers: ordering, duplicates, gaps, measured rates.

Policy (applied by every reader through :func:`check_order` and :func:`find_gaps`):

* A timestamp earlier than the one before it is a :class:`~uavcal_jax.errors.DataError`
  naming the file and the 1-based line.
* A repeated timestamp whose row is identical to the previous row (a duplicated write) is
  dropped with one :class:`~uavcal_jax.errors.DataRepairWarning` listing the lines; a repeated
  timestamp with different values is ambiguous and is a ``DataError``.
* Gaps (intervals longer than ``factor`` nominal periods) are reported, never filled: the
  reader warns with the list of gaps (or raises in strict mode).

``strict=True`` turns every repair warning into a ``DataError``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uavcal_jax.errors import DataError, DataRepairWarning

#: IMU gaps longer than this many nominal periods are reported.
IMU_GAP_FACTOR = 3.0
#: Camera gaps (dropped frames) longer than this many nominal periods are reported.
CAMERA_GAP_FACTOR = 1.5


def repair(message: str, path: str | Path | None, *, strict: bool, stacklevel: int = 3) -> None:
    """Warn that input was repaired (``DataRepairWarning``), or raise ``DataError`` if strict."""
    if strict:
        raise DataError(f"{message} (strict mode: not repaired)", path)
    where = f"{path}: " if path is not None else ""
    warnings.warn(where + message, DataRepairWarning, stacklevel=stacklevel)


def list_lines(lines, limit: int = 20) -> str:
    """``"lines 3, 7, 9"`` (at most ``limit`` listed, then ``"... (N in all)"``)."""
    lines = [int(x) for x in lines]
    text = ", ".join(str(x) for x in lines[:limit])
    if len(lines) > limit:
        text += f", ... ({len(lines)} in all)"
    return ("line " if len(lines) == 1 else "lines ") + text


def check_order(t_ns: np.ndarray, lines: np.ndarray, path: str | Path | None,
                rows: np.ndarray | None = None, *, strict: bool = False) -> np.ndarray:
    """Indices of the rows to keep so that timestamps are strictly increasing.

    Args:
        t_ns: (N,) int64 timestamps in file order.
        lines: (N,) 1-based line numbers of the rows (for messages).
        path: the file, for messages.
        rows: (N, ...) the full row contents; a duplicated timestamp is dropped only when its
            row equals the previous row. ``None``: duplicates are never identical (error).
        strict: raise instead of dropping identical duplicates.

    Raises:
        DataError: a timestamp goes backwards, or repeats with different values.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    if n < 2:
        return np.arange(n)
    d = np.diff(t_ns)
    back = np.flatnonzero(d < 0)
    if back.size:
        i = int(back[0]) + 1
        raise DataError(
            f"timestamps not increasing: {int(t_ns[i])} comes after {int(t_ns[i - 1])} "
            f"(line {int(lines[i - 1])})", path, row=int(lines[i]))
    dup = np.flatnonzero(d == 0) + 1
    if dup.size == 0:
        return np.arange(n)
    for i in dup:
        same = rows is not None and _rows_equal(rows[i], rows[i - 1])
        if not same:
            raise DataError(
                f"duplicate timestamp {int(t_ns[i])} with different values than line "
                f"{int(lines[i - 1])}", path, row=int(lines[i]))
    repair(f"dropped {dup.size} duplicated rows (same timestamp and values as the row before): "
           f"{list_lines(lines[dup])}", path, strict=strict, stacklevel=4)
    keep = np.ones(n, dtype=bool)
    keep[dup] = False
    return np.flatnonzero(keep)


def _rows_equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind == "f" or b.dtype.kind == "f":
        return bool(np.array_equal(a, b, equal_nan=True))
    return bool(np.array_equal(a, b))


@dataclass(frozen=True)
class Gap:
    """An interval between consecutive samples longer than expected.

    Attributes:
        index: index of the sample before the gap (the next sample is ``index + 1``).
        t0_ns / t1_ns: the samples' timestamps on either side of the gap.
        missing: about how many samples are missing, ``round(dt / period) - 1``.
    """

    index: int
    t0_ns: int
    t1_ns: int
    missing: int

    @property
    def duration(self) -> float:
        """Seconds between the samples on either side."""
        return (self.t1_ns - self.t0_ns) * 1e-9

    def as_dict(self) -> dict:
        return {"index": self.index, "t0_ns": self.t0_ns, "t1_ns": self.t1_ns,
                "duration_s": self.duration, "missing": self.missing}

    def __str__(self) -> str:
        return (f"{self.duration * 1e3:.1f} ms after sample {self.index} "
                f"(t={self.t0_ns * 1e-9:.6f} s, ~{self.missing} missing)")


def nominal_period_ns(rate_hz: float | None, t_ns: np.ndarray | None = None) -> int | None:
    """The nominal sample period: ``1/rate_hz``, else the median interval, else ``None``."""
    if rate_hz is not None and rate_hz > 0:
        return int(round(1e9 / float(rate_hz)))
    if t_ns is not None and len(t_ns) >= 2:
        return int(np.median(np.diff(np.asarray(t_ns, dtype=np.int64))))
    return None


def measured_rate_hz(t_ns: np.ndarray) -> float | None:
    """Samples per second from the median interval (robust to gaps), or ``None``."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if t_ns.shape[0] < 2:
        return None
    med = float(np.median(np.diff(t_ns)))
    return 1e9 / med if med > 0 else None


def find_gaps(t_ns: np.ndarray, period_ns: int | None, factor: float) -> list[Gap]:
    """Intervals longer than ``factor * period_ns`` (none when the period is unknown)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if period_ns is None or period_ns <= 0 or t_ns.shape[0] < 2:
        return []
    d = np.diff(t_ns)
    idx = np.flatnonzero(d > factor * period_ns)
    return [Gap(int(i), int(t_ns[i]), int(t_ns[i + 1]),
                max(int(round(d[i] / period_ns)) - 1, 0)) for i in idx]


def describe_gaps(gaps: list[Gap], limit: int = 10) -> str:
    text = "; ".join(str(g) for g in gaps[:limit])
    if len(gaps) > limit:
        text += f"; ... ({len(gaps)} in all)"
    return text
