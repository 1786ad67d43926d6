"""Timestamped text tables (EuRoC CSV, TUM text) read under the readers' bad-input policy.

:func:`read_table` is the one parser every text reader uses (:mod:`uavcal_jax.data.euroc`,
:mod:`uavcal_jax.data.tum`): line-exact :class:`~uavcal_jax.errors.DataError` messages, a
truncated last row dropped with a warning, exact integer-nanosecond timestamps.
:func:`ordered` and :func:`drop_non_finite` apply the timestamp-order and NaN/inf rules of
:mod:`uavcal_jax.data.timing` to a :class:`Table`.
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from uavcal_jax.data.timing import check_order, list_lines, repair
from uavcal_jax.errors import DataError

__all__ = ["Table", "drop_non_finite", "ordered", "parse_seconds_ns", "read_table"]


@dataclass(frozen=True)
class Table:
    """Rows of a timestamped text table, after the bad-input policy.

    Attributes:
        path: the file.
        t_ns: (N,) int64 timestamps.
        values: (N, k) float64 (numeric tables) or (N, k) str (``numeric=False``).
        lines: (N,) int64 1-based line numbers of the rows in the file.
    """

    path: Path
    t_ns: np.ndarray
    values: np.ndarray
    lines: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def take(self, idx: np.ndarray) -> Table:
        return Table(self.path, self.t_ns[idx], self.values[idx], self.lines[idx])


def parse_seconds_ns(text: str) -> int:
    """Exact int nanoseconds from decimal seconds text (round half to even)."""
    value = Decimal(text.strip()) * 1_000_000_000
    if not value.is_finite():
        raise ValueError(f"non-finite time {text!r}")
    return int(value.to_integral_value())


def read_table(path: str | Path, n_fields: int, *, sep: str | None = ",",
               time_unit: str = "ns", numeric: bool = True, strict: bool = False) -> Table:
    """Read a timestamped text table (EuRoC CSV, TUM text) with line-exact error messages.

    Blank lines and lines starting with ``#`` are skipped. The first field is the timestamp:
    integer nanoseconds (``time_unit="ns"``) or decimal seconds converted exactly to int64
    nanoseconds (``time_unit="s"``). The other ``n_fields - 1`` fields are float64 (or kept as
    stripped strings when ``numeric=False``).

    Args:
        sep: field separator; ``None`` splits on whitespace.

    Raises:
        DataError: missing/unreadable file, or a malformed row other than the last one (a
            malformed *last* row is dropped with a ``DataRepairWarning``, unless ``strict``).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError("missing file", path)
    try:
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read text file: {err}", path) from None

    body: list[str] = []
    linenos: list[int] = []
    for lineno, raw in enumerate(text.split("\n"), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            body.append(line)
            linenos.append(lineno)
    fields = [ln.split(sep) for ln in body]
    if sep is not None:
        fields = [[f.strip() for f in row] for row in fields]

    def bad_row(k: int, reason: str) -> None:
        if k == len(body) - 1:
            repair(f"dropped the truncated last row (line {linenos[k]}: {reason})", path,
                   strict=strict, stacklevel=5)
        else:
            raise DataError(f"malformed row: {reason}", path, row=linenos[k])

    # Field counts.
    wrong = [k for k, row in enumerate(fields) if len(row) != n_fields]
    for k in wrong:
        bad_row(k, f"{len(fields[k])} fields, expected {n_fields}")
    if wrong:  # only the last row can get here
        fields, linenos = fields[:-1], linenos[:-1]
        body = body[:-1]

    n = len(fields)
    if n == 0:
        return Table(path, np.zeros(0, np.int64),
                     np.zeros((0, n_fields - 1), np.float64 if numeric else str),
                     np.zeros(0, np.int64))

    # Fast vectorised conversion; on failure, locate the first bad row.
    try:
        if time_unit == "ns":
            t_ns = np.array([row[0] for row in fields]).astype(np.int64)
        elif time_unit == "s":
            t_ns = np.array([parse_seconds_ns(row[0]) for row in fields], dtype=np.int64)
        else:
            raise ValueError(f"time_unit must be 'ns' or 's', got {time_unit!r}")
        if numeric:
            values = np.array([row[1:] for row in fields], dtype=np.float64)
        else:
            values = np.array([row[1:] for row in fields], dtype=str)
        if not numeric and (values == "").any():
            raise ValueError("empty field")
    except (ValueError, OverflowError, InvalidOperation, ArithmeticError):
        if time_unit not in ("ns", "s"):
            raise
        keep = np.ones(n, dtype=bool)
        for k, row in enumerate(fields):
            reason = _row_error(row, time_unit, numeric)
            if reason is not None:
                bad_row(k, reason)
                keep[k] = False  # only the last row
        fields = [row for k, row in enumerate(fields) if keep[k]]
        linenos = [ln for k, ln in enumerate(linenos) if keep[k]]
        return _table_from_fields(path, fields, linenos, time_unit, numeric, n_fields)
    return Table(path, t_ns, values.reshape(n, n_fields - 1), np.asarray(linenos, np.int64))


def _row_error(row: list[str], time_unit: str, numeric: bool) -> str | None:
    try:
        if time_unit == "ns":
            int(row[0])
        else:
            parse_seconds_ns(row[0])
    except (ValueError, InvalidOperation, ArithmeticError):
        return f"bad timestamp {row[0]!r}"
    if numeric:
        for j, v in enumerate(row[1:], start=2):
            try:
                float(v)
            except ValueError:
                return f"field {j} is not a number: {v!r}"
    elif any(v == "" for v in row[1:]):
        return "empty field"
    return None


def _table_from_fields(path: Path, fields: list[list[str]], linenos: list[int],
                       time_unit: str, numeric: bool, n_fields: int) -> Table:
    n = len(fields)
    if time_unit == "ns":
        t_ns = np.array([int(row[0]) for row in fields], dtype=np.int64)
    else:
        t_ns = np.array([parse_seconds_ns(row[0]) for row in fields], dtype=np.int64)
    dtype = np.float64 if numeric else str
    values = np.array([row[1:] for row in fields], dtype=dtype).reshape(n, n_fields - 1)
    return Table(path, t_ns.reshape(n), values, np.asarray(linenos, np.int64).reshape(n))


def drop_non_finite(table: Table, *, strict: bool, what: str = "rows") -> Table:
    """Drop rows with NaN/inf values (one warning listing the lines; ``DataError`` if strict)."""
    if len(table) == 0:
        return table
    bad = ~np.all(np.isfinite(table.values), axis=1)
    if not bad.any():
        return table
    repair(f"dropped {int(bad.sum())} {what} with NaN/inf values: {list_lines(table.lines[bad])}",
           table.path, strict=strict, stacklevel=4)
    return table.take(np.flatnonzero(~bad))


def ordered(table: Table, *, strict: bool) -> Table:
    """Apply the timestamp-order policy of :func:`uavcal_jax.data.timing.check_order`."""
    keep = check_order(table.t_ns, table.lines, table.path, table.values, strict=strict)
    return table if keep.shape[0] == len(table) else table.take(keep)
