"""The calibrator's motion inputs that come from another task package: the camera's relative
rotations for ``window.rotations=visual`` (issue 20) and the VIO's metric trajectory for
``window.accel_start=alignment`` (issue 43).

calib may not import the VIO, so it takes these as callables: the front end's frame-to-frame
body rotations of a recording (:func:`uavcal_jax.vio.visual_rotation.relative_rotations`,
computed once and cached beside it, :mod:`uavcal_jax.vio.rotation_cache`), which never see
the gyro. :func:`sequence_rotations` is that of a recording already read (an estimator's, which
must not read the folder again: :func:`uavcal_jax.calib.predict.predict_on_sequence`'s
``rotation_source``); :func:`visual_rotation_source` that of a training folder
(:func:`uavcal_jax.calib.data.load_windows`'s), read only when nothing is cached;
:func:`sequence_poses` and :func:`vio_pose_source` the same for the VIO's poses.
:func:`folder_sources` and :func:`sequence_sources` give the ones a window configuration
needs, as keyword arguments.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.data.windows import WindowConfig
from uavcal_jax.vio.pose_cache import VioPoses, cached_vio_poses, read_pose_cache
from uavcal_jax.vio.rotation_cache import cached_relative_rotations, read_cache
from uavcal_jax.vio.visual_rotation import VisualRotations

__all__ = ["folder_sources", "sequence_poses", "sequence_rotations", "sequence_sources",
           "visual_rotation_source", "vio_pose_source"]


def sequence_rotations(sequence: Sequence) -> VisualRotations:
    """The relative body rotations between consecutive left-camera frames of ``sequence``
    (``R[k]``: body frame at ``t0_ns[k]`` from ``t1_ns[k]``), cached in its folder."""
    return cached_relative_rotations(sequence)


def visual_rotation_source(folder: str | Path) -> VisualRotations:
    """:func:`sequence_rotations` of the EuRoC recording in ``folder`` (read only on a cache
    miss)."""
    cached = read_cache(folder)
    return cached if cached is not None else sequence_rotations(read_euroc(Path(folder)))


def sequence_poses(sequence: Sequence) -> VioPoses:
    """The stereo VIO's trajectory over ``sequence``'s recorded IMU, cached in its folder (the
    VIO never sees a ground truth: it is taken away first)."""
    return cached_vio_poses(dataclasses.replace(sequence, ground_truth=None))


def vio_pose_source(folder: str | Path) -> VioPoses:
    """:func:`sequence_poses` of the EuRoC recording in ``folder`` (read only on a miss)."""
    cached = read_pose_cache(folder)
    return cached if cached is not None else sequence_poses(read_euroc(Path(folder)))


def folder_sources(window: WindowConfig) -> dict:
    """The ``rotation_source`` and ``pose_source`` of
    :func:`uavcal_jax.calib.data.load_windows` that ``window`` needs (training folders)."""
    return {"rotation_source": visual_rotation_source if window.rotations == "visual" else None,
            "pose_source": vio_pose_source if window.accel_start == "alignment" else None}


def sequence_sources(window: WindowConfig) -> dict:
    """The same for :func:`uavcal_jax.calib.predict.predict_on_sequence` (a recording already
    read)."""
    return {"rotation_source": sequence_rotations if window.rotations == "visual" else None,
            "pose_source": sequence_poses if window.accel_start == "alignment" else None}
