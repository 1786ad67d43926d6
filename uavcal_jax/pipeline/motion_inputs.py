"""The calibrator's motion inputs that come from another task package: the camera's relative
rotations for ``window.rotations=visual`` (issue 20).

calib may not import the VIO, so it takes these as callables: the front end's frame-to-frame
body rotations of a recording (:func:`uavcal_jax.vio.visual_rotation.relative_rotations`,
computed once and cached beside it, :mod:`uavcal_jax.vio.rotation_cache`), which never see
the gyro. :func:`sequence_rotations` is that of a recording already read (an estimator's, which
must not read the folder again: :func:`uavcal_jax.calib.predict.predict_on_sequence`'s
``rotation_source``); :func:`visual_rotation_source` that of a training folder
(:func:`uavcal_jax.calib.data.load_windows`'s), read only when nothing is cached.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.vio.rotation_cache import cached_relative_rotations, read_cache
from uavcal_jax.vio.visual_rotation import VisualRotations

__all__ = ["sequence_rotations", "visual_rotation_source"]


def sequence_rotations(sequence: Sequence) -> VisualRotations:
    """The relative body rotations between consecutive left-camera frames of ``sequence``
    (``R[k]``: body frame at ``t0_ns[k]`` from ``t1_ns[k]``), cached in its folder."""
    return cached_relative_rotations(sequence)


def visual_rotation_source(folder: str | Path) -> VisualRotations:
    """:func:`sequence_rotations` of the EuRoC recording in ``folder`` (read only on a cache
    miss)."""
    cached = read_cache(folder)
    return cached if cached is not None else sequence_rotations(read_euroc(Path(folder)))
