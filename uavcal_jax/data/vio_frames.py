"""The VIO's per-frame table, ``TRAJ.frames.csv`` beside ``uavcal vio``'s trajectory.

CSV with the header row :data:`FRAME_COLUMNS`, then one row per left frame: ``t_ns`` (int
ns), ``status`` and ``reason`` (the estimator's status and why: text), ``keyframe`` (0 or 1),
``tracked``, ``stereo``, ``landmarks``, ``iterations`` (ints), ``cost`` (the solved window
cost, ``%.6g``), then the stages' milliseconds to ``%.3f``: ``frontend_ms``, ``solve_ms``,
``marginalize_ms`` and ``total_ms``.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

__all__ = ["FRAME_COLUMNS", "write_frames_csv"]

#: The header, in column order.
FRAME_COLUMNS = ("t_ns", "status", "reason", "keyframe", "tracked", "stereo", "landmarks",
                 "iterations", "cost", "frontend_ms", "solve_ms", "marginalize_ms", "total_ms")


def write_frames_csv(path: str | Path, rows: Iterable[tuple]) -> Path:
    """Write ``rows``, one tuple per frame in :data:`FRAME_COLUMNS`' order (``keyframe`` a
    bool, ``cost`` and the milliseconds floats). Returns ``path``."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FRAME_COLUMNS)
        for t_ns, status, reason, keyframe, *counts, cost, f_ms, s_ms, m_ms, t_ms in rows:
            w.writerow([t_ns, status, reason, int(keyframe), *counts, f"{cost:.6g}",
                        *(f"{ms:.3f}" for ms in (f_ms, s_ms, m_ms, t_ms))])
    return path
