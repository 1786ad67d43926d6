"""Command-line value types and JSON output shared by the ``uavcal`` commands and the
experiment scripts (so neither imports the other)."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

__all__ = ["fraction", "parse_imgsz", "parse_offset", "parse_resolution", "parse_vector3",
           "positive",
           "positive_int", "print_json", "to_builtin"]


def parse_resolution(text: str) -> tuple[int, int]:
    """``"752x480"`` -> ``(752, 480)`` as ``(width, height)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT, e.g. 752x480, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"resolution must be at least 8x8, got {text!r}")
    return w, h


def parse_imgsz(text: str) -> tuple[int, int]:
    """``"640"`` -> (640, 640); ``"640x480"`` (width x height) -> (480, 640) as (H, W)."""
    try:
        parts = [int(v) for v in text.lower().replace(",", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected S or WxH, e.g. 640x480, got {text!r}") \
            from None
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected S or WxH, got {text!r}")
    w, h = parts
    if w % 32 or h % 32 or w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"image size must be multiples of 32, got {text!r}")
    return h, w


def _comma_floats(text: str, names: str, what: str) -> tuple[float, ...]:
    """``text`` as the finite floats named by ``names`` (``"X,Y,Z"``: 3 of them)."""
    n = names.count(",") + 1
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {n} comma-separated numbers {names}, got {text!r}") from None
    if len(values) != n:
        raise argparse.ArgumentTypeError(
            f"expected {n} comma-separated numbers {names}, got {len(values)} in {text!r}")
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"{what} values must be finite, got {text!r}")
    return values


def parse_offset(text: str) -> tuple[float, ...]:
    """``"GX,GY,GZ,AX,AY,AZ"`` -> an IMU offset, 6 finite floats (gyro rad/s xyz, accel m/s^2
    xyz, the order of :mod:`uavcal_jax.imu.offset`). A first value below zero needs the
    ``--option=-0.01,...`` form (argparse takes a lone ``-0.01,...`` for an option)."""
    return _comma_floats(text, "GX,GY,GZ,AX,AY,AZ", "offset")


def parse_vector3(text: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` -> 3 finite floats (``--option=-1,...`` when the first is negative)."""
    return _comma_floats(text, "X,Y,Z", "vector")  # type: ignore[return-value]


def positive(text: str) -> float:
    """A float > 0."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def positive_int(text: str) -> int:
    """An int >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def fraction(text: str) -> float:
    """A float in [0, 1]."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def to_builtin(value: Any) -> Any:
    """``json.dumps``'s ``default``: NumPy scalars and arrays, and paths, as built-ins."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__fspath__"):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def print_json(obj: Any) -> None:
    """Print ``obj`` as one JSON object on one line (numpy values converted)."""
    print(json.dumps(obj, default=to_builtin))
