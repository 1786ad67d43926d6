"""Progress bars for long work (tqdm on stderr, silent when disabled or under ``--json``)."""

from __future__ import annotations

import sys
from collections.abc import Iterable

from tqdm.auto import tqdm


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
             enabled: bool = True, unit: str = "it"):
    """A tqdm bar on stderr; silent when ``enabled`` is false."""
    return tqdm(iterable, total=total, desc=desc, disable=not enabled, unit=unit,
                file=sys.stderr, dynamic_ncols=True, leave=False)
