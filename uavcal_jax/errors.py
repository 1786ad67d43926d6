"""Errors and warnings raised on bad input.

Every reader raises :class:`DataError` with the offending file (and row where there is one)
in the message, or repairs the input and emits :class:`DataRepairWarning` saying what it did.
"""

from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """Input data is missing, corrupt or inconsistent.

    Attributes:
        path: the file or folder at fault (``None`` when not file-backed).
        row: 1-based line number in that file, when the fault is on one line.
    """

    def __init__(self, message: str, path: str | Path | None = None, row: int | None = None):
        self.path = None if path is None else Path(path)
        self.row = row
        where = ""
        if self.path is not None:
            where = f"{self.path}"
            if row is not None:
                where += f", line {row}"
            where += ": "
        super().__init__(where + message)


class DataRepairWarning(UserWarning):
    """Input was repaired (rows dropped, frames skipped, values clipped); the message says how."""


class OutOfDomainWarning(UserWarning):
    """A learned estimator meets data unlike what it was trained on (the message says how it
    differs and what to use instead); its output is unreliable."""


class FlightLimitWarning(UserWarning):
    """A flight exceeds what a drone can fly (the message gives the peak and the limit); the
    recording is written, but its IMU is probably not a real one's."""
