"""TUM trajectory files: ``t tx ty tz qx qy qz qw`` per line, ``#`` comments.

``t`` is in seconds (decimal text); it is converted to int64 nanoseconds *exactly* (decimal
arithmetic, rounded half to even at the nanosecond), never through float64, so a file's own
timestamps survive a round trip. Quaternions are stored x, y, z, w in the file and returned
w, x, y, z (the project's convention). Fields are separated by whitespace (or commas, when the
first data line has one).

Bad-input policy (that of :mod:`uavcal_jax.data.table`, as for EuRoC): a malformed row is a
:class:`~uavcal_jax.errors.DataError` naming the file and 1-based line, except a truncated
last row, which is dropped with a :class:`~uavcal_jax.errors.DataRepairWarning`; timestamps
going backwards are an error; identical duplicated rows are dropped with a warning; rows with
NaN/inf are dropped with a warning; a quaternion whose norm is not 1 within 1e-3 is an error
(it is not a rotation). ``strict=True`` turns every repair into an error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.table import drop_non_finite, ordered, read_table
from uavcal_jax.errors import DataError

HEADER = "# timestamp tx ty tz qx qy qz qw"

#: Largest accepted deviation of a quaternion's norm from 1.
QUATERNION_NORM_TOLERANCE = 1e-3


def _separator(path: Path) -> str | None:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            for line in f:
                s = line.strip()
                if s and not s.startswith("#"):
                    return "," if "," in s else None
    except OSError:
        pass
    return None


def read_tum(path: str | Path, *, strict: bool = False) -> GroundTruth:
    """Read a TUM trajectory file into :class:`GroundTruth` (no velocity or biases).

    Returns:
        ``GroundTruth`` with ``t_ns`` (int64, exact), ``position`` (N, 3) and ``quaternion``
        (N, 4) in w, x, y, z order, as written in the file (not renormalised).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError("missing TUM trajectory file", path)
    table = read_table(path, 8, sep=_separator(path), time_unit="s", strict=strict)
    table = ordered(table, strict=strict)
    table = drop_non_finite(table, strict=strict, what="poses")
    if len(table) == 0:
        raise DataError("no poses in TUM trajectory file", path)
    v = table.values
    quat = np.ascontiguousarray(v[:, [6, 3, 4, 5]])
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        k = int(bad[0])
        raise DataError(f"quaternion norm {norm[k]:.6g} is not 1 ({bad.size} such rows)", path,
                        row=int(table.lines[k]))
    return GroundTruth(t_ns=table.t_ns, position=np.ascontiguousarray(v[:, 0:3]),
                       quaternion=quat)


def format_ns_seconds(t_ns: int) -> str:
    """Exact decimal seconds text of an integer nanosecond time (``1.000000001``)."""
    t_ns = int(t_ns)
    sign = "-" if t_ns < 0 else ""
    s, ns = divmod(abs(t_ns), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def write_tum(path: str | Path, ground_truth: GroundTruth, *, header: bool = True) -> Path:
    """Write ``ground_truth`` (t, position, quaternion w,x,y,z) as a TUM file.

    Times are written as exact decimal seconds with 9 digits, values with ``repr`` (shortest
    text that reads back to the same float64), so :func:`read_tum` returns identical arrays.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t_ns = np.asarray(ground_truth.t_ns, dtype=np.int64)
    pos = np.asarray(ground_truth.position, dtype=np.float64)
    quat = np.asarray(ground_truth.quaternion, dtype=np.float64)
    if pos.shape != (t_ns.shape[0], 3) or quat.shape != (t_ns.shape[0], 4):
        raise ValueError(f"shapes disagree: t {t_ns.shape}, position {pos.shape}, "
                         f"quaternion {quat.shape}")
    lines = [HEADER] if header else []
    xyzw = quat[:, [1, 2, 3, 0]]
    for t, p, q in zip(t_ns, pos, xyzw, strict=True):
        lines.append(" ".join([format_ns_seconds(t), *(repr(float(x)) for x in p),
                               *(repr(float(x)) for x in q)]))
    path.write_text("\n".join(lines) + "\n")
    return path
