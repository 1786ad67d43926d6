"""The calibrator's motion inputs that come from another task package: the camera's relative
rotations for ``window.rotations=visual`` (issue 20).

:func:`uavcal_jax.calib.data.load_windows` takes a ``rotation_source`` callable, since calib
may not import the VIO; :func:`visual_rotation_source` is that callable: the front end's
frame-to-frame body rotations of a recording
(:func:`uavcal_jax.vio.visual_rotation.cached_relative_rotations`, computed once and cached
beside it), which never see the gyro.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.vio.visual_rotation import VisualRotations, cached_relative_rotations

__all__ = ["visual_rotation_source"]


def visual_rotation_source(folder: str | Path) -> VisualRotations:
    """The relative body rotations between consecutive left-camera frames of the EuRoC
    recording in ``folder`` (``R[k]``: body frame at ``t0_ns[k]`` from ``t1_ns[k]``)."""
    return cached_relative_rotations(Path(folder))
