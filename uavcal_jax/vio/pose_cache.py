"""A recording's stereo VIO trajectory (metric poses and the gyro bias per frame), computed once
and kept beside it: the calibrator's metric accelerometer start
(:mod:`uavcal_jax.data.window_alignment`) reads it for every window.

As :mod:`uavcal_jax.vio.rotation_cache`: :func:`cached_vio_poses` takes the recording already
read (a :class:`~uavcal_jax.data.sequence.Sequence`, which an estimator gets without its
ground truth) and runs the VIO on its recorded IMU; the folder only holds the file, named by
the VIO's settings. :func:`read_pose_cache` reads a folder's file without the sequence.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import NamedTuple

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.npz_cache import settings_tag, write_npz_atomic
from uavcal_jax.vio.run import run_vio

__all__ = ["VioPoses", "cached_vio_poses", "pose_cache_path", "read_pose_cache", "vio_poses"]

#: Bumped when what is stored changes, so old files are not reused.
_CACHE_VERSION = 1
_CACHE_PREFIX = "vio_poses"
#: Frame statuses whose pose counts as tracked (solved with landmarks).
TRACKED = ("tracking",)


class VioPoses(NamedTuple):
    """The VIO's estimate at every left frame with a pose.

    Attributes:
        t_ns: (M,) int64 frame times.
        position: (M, 3) m, world (gravity-aligned, z up).
        rotation: (M, 3, 3) body (IMU) to world.
        bias_gyro: (M, 3) rad/s, the VIO's gyro bias state (the recorded IMU's whole
            constant gyro error as the VIO sees it).
        tracked: (M,) bool, the frame was solved with landmarks (not initialising, coasting
            or reset).
    """

    t_ns: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    bias_gyro: np.ndarray
    tracked: np.ndarray


def vio_poses(sequence: Sequence, config: VioConfig | None = None, *,
              progress: bool = False) -> VioPoses:
    """The VIO (:func:`~uavcal_jax.vio.run.run_vio`) over ``sequence``'s recorded IMU."""
    result = run_vio(sequence, config, show_progress=progress)
    frames = [f for f in result.frames if f.has_pose]
    if not frames:
        return VioPoses(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                        np.zeros((0, 3)), np.zeros(0, bool))
    return VioPoses(np.array([f.t_ns for f in frames], np.int64),
                    np.stack([f.position for f in frames]).astype(np.float64),
                    np.stack([f.rotation for f in frames]).astype(np.float64),
                    np.stack([f.bias_gyro for f in frames]).astype(np.float64),
                    np.array([f.status in TRACKED for f in frames]))


def pose_cache_path(folder: str | Path, config: VioConfig | None = None) -> Path:
    """``<folder>/vio_poses.<8 hex digits of the VIO's settings>.npz``."""
    config = VioConfig() if config is None else config
    tag = settings_tag({"version": _CACHE_VERSION, "vio": dataclasses.asdict(config)})
    return Path(folder) / f"{_CACHE_PREFIX}.{tag}.npz"


def read_pose_cache(folder: str | Path, config: VioConfig | None = None) -> VioPoses | None:
    """The poses cached in ``folder`` under ``config``, or ``None``."""
    path = pose_cache_path(folder, config)
    if not path.is_file():
        return None
    with np.load(path) as z:
        return VioPoses(**{name: z[name] for name in VioPoses._fields})


def cached_vio_poses(sequence: Sequence, config: VioConfig | None = None, *,
                     progress: bool = False) -> VioPoses:
    """:func:`vio_poses` of ``sequence``, kept in :func:`pose_cache_path` of its folder
    (``sequence.root``; none without a folder, a warning where it cannot be written)."""
    folder = sequence.root
    if folder is not None and Path(folder).is_dir():
        cached = read_pose_cache(folder, config)
        if cached is not None:
            return cached
    poses = vio_poses(sequence, config, progress=progress)
    if folder is not None and Path(folder).is_dir():
        write_npz_atomic(pose_cache_path(folder, config), poses._asdict(), "VIO poses")
    return poses
