"""The camera's relative rotations of a recording (:func:`~uavcal_jax.vio.visual_rotation.
relative_rotations`), computed once and kept beside it.

:func:`cached_relative_rotations` takes the recording already read (a
:class:`~uavcal_jax.data.sequence.Sequence`): it computes from the sequence's frames and never
reads the folder again (an estimator is given a sequence without ground truth, and nothing here
brings it back); the folder (``sequence.root``) only holds the cache file, named by the
settings (:func:`cache_path`). :func:`read_cache` reads a folder's cache without the sequence
(the calibrator's training, which reads the recording only on a miss).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.vio.config import FrontendConfig
from uavcal_jax.vio.npz_cache import settings_tag, write_npz_atomic
from uavcal_jax.vio.visual_rotation import (
    MIN_PARALLAX_PX,
    MIN_TRACKS,
    VisualRotations,
    relative_rotations,
)

__all__ = ["cache_path", "cached_relative_rotations", "read_cache"]

#: Bumped when the estimate changes, so old caches are not reused.
_CACHE_VERSION = 1
_CACHE_PREFIX = "visual_rotations"


def _cache_tag(frontend: FrontendConfig, every: int, min_tracks: int, min_parallax_px: float,
               camera: str) -> str:
    return settings_tag({"version": _CACHE_VERSION, "camera": camera, "every": every,
                         "min_tracks": min_tracks, "min_parallax_px": min_parallax_px,
                         "frontend": dataclasses.asdict(frontend)})


def cache_path(folder: str | Path, frontend: FrontendConfig | None = None, *, every: int = 1,
               min_tracks: int = MIN_TRACKS, min_parallax_px: float = MIN_PARALLAX_PX,
               camera: str = "cam0") -> Path:
    """``<folder>/visual_rotations.<8 hex digits of the settings>.npz`` (the settings of
    :func:`~uavcal_jax.vio.visual_rotation.relative_rotations`)."""
    frontend = frontend if frontend is not None else FrontendConfig()
    tag = _cache_tag(frontend, every, min_tracks, min_parallax_px, camera)
    return Path(folder) / f"{_CACHE_PREFIX}.{tag}.npz"


def read_cache(folder: str | Path, frontend: FrontendConfig | None = None, *, every: int = 1,
               min_tracks: int = MIN_TRACKS, min_parallax_px: float = MIN_PARALLAX_PX,
               camera: str = "cam0") -> VisualRotations | None:
    """The rotations cached in ``folder`` under these settings, or ``None`` (no cache)."""
    path = cache_path(folder, frontend, every=every, min_tracks=min_tracks,
                      min_parallax_px=min_parallax_px, camera=camera)
    if not path.is_file():
        return None
    with np.load(path) as z:
        return VisualRotations(**{name: z[name] for name in VisualRotations._fields})


def cached_relative_rotations(sequence: Sequence, frontend: FrontendConfig | None = None, *,
                              every: int = 1, min_tracks: int = MIN_TRACKS,
                              min_parallax_px: float = MIN_PARALLAX_PX, camera: str = "cam0",
                              progress: bool = False) -> VisualRotations:
    """:func:`~uavcal_jax.vio.visual_rotation.relative_rotations` of ``sequence`` (same
    arguments), kept in :func:`cache_path` of its folder ``sequence.root`` (written to a
    temporary file and renamed, so an interrupted run leaves no half file). A sequence with no
    folder is not cached; a folder that cannot be written to (a read-only dataset) gives the
    result with a warning and no cache."""
    settings = {"every": every, "min_tracks": min_tracks, "min_parallax_px": min_parallax_px,
                "camera": camera}
    folder = sequence.root
    if folder is not None and Path(folder).is_dir():
        cached = read_cache(folder, frontend, **settings)
        if cached is not None:
            return cached
    rot = relative_rotations(sequence, frontend, progress=progress, **settings)
    if folder is None or not Path(folder).is_dir():
        return rot
    write_npz_atomic(cache_path(folder, frontend, **settings), rot._asdict(),
                     "visual rotations")
    return rot
