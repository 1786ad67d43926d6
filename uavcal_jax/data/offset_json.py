"""The IMU offset file: the calibrator's output and ``uavcal vio --offsets``' input.

One JSON object whose ``"offset"`` is 6 finite numbers, gyro rad/s xyz then accel m/s^2 xyz
(the order of :mod:`uavcal_jax.imu.offset`): the constant error present in the recorded IMU,
removed by ``sample - offset``. Other keys (per-window estimates, the true offset, errors)
may sit beside it and are ignored by the reader.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from uavcal_jax.errors import DataError

__all__ = ["OFFSET_KEY", "read_offset_json", "write_offset_json"]

#: The key holding the 6-vector.
OFFSET_KEY = "offset"


def read_offset_json(path: str | Path) -> np.ndarray:
    """The (6,) offset in ``path``.

    Raises:
        DataError: missing or unreadable file, not JSON, no ``"offset"``, not 6 finite numbers.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: offset file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not a readable JSON offset file ({exc})") from None
    if not isinstance(data, dict) or OFFSET_KEY not in data:
        raise DataError(f"{path}: expected a JSON object with an {OFFSET_KEY!r} key holding "
                        "6 numbers (gyro rad/s xyz, accel m/s^2 xyz)")
    try:
        offset = np.asarray(data[OFFSET_KEY], dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{path}: {OFFSET_KEY!r} must be 6 numbers") from None
    if offset.shape != (6,) or not np.all(np.isfinite(offset)):
        raise DataError(f"{path}: {OFFSET_KEY!r} must be 6 finite numbers, got "
                        f"{data[OFFSET_KEY]!r}")
    return offset


def write_offset_json(path: str | Path, offset, **extra) -> Path:
    """Write ``{"offset": [...6], **extra}`` atomically (a temporary file renamed)."""
    path = Path(path)
    offset = np.asarray(offset, np.float64).reshape(6)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps({OFFSET_KEY: offset.tolist(), **extra}, indent=2) + "\n")
    tmp.replace(path)
    return path
