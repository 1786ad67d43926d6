"""An array record kept beside a recording: written atomically, skipped (with a warning) where
the folder cannot be written to. The caches of :mod:`uavcal_jax.vio.rotation_cache` and
:mod:`uavcal_jax.vio.pose_cache` share it."""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

__all__ = ["settings_tag", "write_npz_atomic"]


def settings_tag(fields: dict) -> str:
    """8 hex digits of a JSON-ready settings dict (a cache file's name part)."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:8]


def write_npz_atomic(path: Path, arrays: dict[str, np.ndarray], what: str) -> None:
    """``np.savez`` of ``arrays`` to ``path`` through a temporary file renamed into place (an
    interrupted run leaves no half file); a folder that cannot be written to (a read-only
    dataset) gives a warning naming ``what`` and no file."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:
        warnings.warn(f"{path}: {what} not cached ({e})", stacklevel=3)
