"""Helpers shared by the sub-commands: JSON output and progress bars."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable
from typing import Any

import numpy as np
from tqdm.auto import tqdm


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


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
             enabled: bool = True, unit: str = "it"):
    """A tqdm bar on stderr; silent when ``enabled`` is false (e.g. under ``--json``)."""
    return tqdm(iterable, total=total, desc=desc, disable=not enabled, unit=unit,
                file=sys.stderr, dynamic_ncols=True, leave=False)
