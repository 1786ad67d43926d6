"""The tables ``uavcal run`` writes beside its trajectory: ``targets.csv`` and
``setpoints.csv`` (names and headers fixed, so that scripts can rely on them).

``targets.csv``, header :data:`TARGETS_HEADER`: one row per frame and target estimate,
``t_ns`` (int ns, the left frame), ``track_id`` (int), ``class`` (name), ``x, y, z`` (world
metres, the trajectory's frame), ``var_x, var_y, var_z`` (the position covariance's
diagonal, m^2), ``confidence`` (in [0, 1]) and ``kind``: ``raw`` (one frame's localisation) or
``filtered`` (the filter's estimate).

``setpoints.csv``, header :data:`SETPOINTS_HEADER`: one row per left frame, ``t_ns``, the
position set-point ``x, y, z`` (world metres) and ``yaw`` (radians about world z, in
``[-pi, pi)``).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from uavcal_jax.errors import DataError

__all__ = ["SETPOINTS_HEADER", "TARGETS_HEADER", "TARGET_KINDS", "read_setpoints",
           "read_targets", "write_setpoints", "write_targets"]

TARGETS_HEADER = ("t_ns", "track_id", "class", "x", "y", "z", "var_x", "var_y", "var_z",
                  "confidence", "kind")
SETPOINTS_HEADER = ("t_ns", "x", "y", "z", "yaw")
#: ``targets.csv``'s ``kind`` values.
TARGET_KINDS = ("raw", "filtered")


def write_targets(path: str | Path, rows) -> Path:
    """Write ``rows``: tuples ``(t_ns, track_id, class, (x, y, z), (var_x, var_y, var_z),
    confidence, kind)``. Returns ``path``."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TARGETS_HEADER)
        for t_ns, track_id, name, p, var, conf, kind in rows:
            if kind not in TARGET_KINDS:
                raise ValueError(f"kind must be one of {TARGET_KINDS}, got {kind!r}")
            w.writerow([int(t_ns), int(track_id), name, *(f"{v:.6f}" for v in p),
                        *(f"{v:.6g}" for v in var), f"{conf:.4f}", kind])
    return path


def write_setpoints(path: str | Path, t_ns, position, yaw) -> Path:
    """Write ``t_ns`` (T,), ``position`` (T, 3) and ``yaw`` (T,). Returns ``path``."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(SETPOINTS_HEADER)
        for t, p, a in zip(t_ns, position, yaw, strict=True):
            w.writerow([int(t), *(f"{v:.6f}" for v in p), f"{a:.6f}"])
    return path


def _rows(path: Path, header: tuple[str, ...]) -> list[list[str]]:
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as err:
        raise DataError(f"cannot read ({err})", path) from None
    if not rows or tuple(rows[0]) != header:
        raise DataError(f"expected the header {','.join(header)}", path)
    return rows[1:]


def read_targets(path: str | Path) -> dict[str, np.ndarray]:
    """``targets.csv`` as columns by header name (numbers as int64 / float64).

    Raises:
        DataError: another header, a malformed row (named by its line), a non-finite value.
    """
    path = Path(path)
    out: dict[str, list] = {k: [] for k in TARGETS_HEADER}
    for line, row in enumerate(_rows(path, TARGETS_HEADER), start=2):
        try:
            if len(row) != len(TARGETS_HEADER) or row[-1] not in TARGET_KINDS:
                raise ValueError("malformed row")
            values = [int(row[0]), int(row[1]), row[2], *map(float, row[3:10]), row[10]]
            if not np.all(np.isfinite(values[3:10])):
                raise ValueError("non-finite value")
        except ValueError as err:
            raise DataError(str(err), path, line) from None
        for key, value in zip(TARGETS_HEADER, values, strict=True):
            out[key].append(value)
    return {k: np.asarray(v, dtype=np.int64 if k in ("t_ns", "track_id") else
                          (str if k in ("class", "kind") else np.float64))
            for k, v in out.items()}


def read_setpoints(path: str | Path) -> dict[str, np.ndarray]:
    """``setpoints.csv`` as columns by header name.

    Raises:
        DataError: another header, a malformed row (named by its line), a non-finite value.
    """
    path = Path(path)
    rows = []
    for line, row in enumerate(_rows(path, SETPOINTS_HEADER), start=2):
        try:
            if len(row) != len(SETPOINTS_HEADER):
                raise ValueError("malformed row")
            values = [int(row[0]), *map(float, row[1:])]
            if not np.all(np.isfinite(values[1:])):
                raise ValueError("non-finite value")
        except ValueError as err:
            raise DataError(str(err), path, line) from None
        rows.append(values)
    a = np.asarray(rows, np.float64).reshape(-1, 5)
    return {"t_ns": np.asarray([r[0] for r in rows], np.int64), "x": a[:, 1], "y": a[:, 2],
            "z": a[:, 3], "yaw": a[:, 4]}
