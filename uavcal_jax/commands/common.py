"""Helpers shared by the sub-commands: JSON output."""

from __future__ import annotations

import json
from typing import Any

import numpy as np


def _to_builtin(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__fspath__"):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def print_json(obj: Any) -> None:
    """Print ``obj`` as one JSON object on one line (numpy values converted)."""
    print(json.dumps(obj, default=_to_builtin))
