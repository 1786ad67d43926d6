"""How the simulated stereo rig sits on the drone: its pitch below the forward axis.

Frames. ``B`` is the body (IMU) frame, EuRoC's convention (x up, z forward); ``Q`` is the
quadrotor frame (x forward, y left, z up) in which EuRoC's IMU is mounted by
``R_QB = euroc_imu_mounting()`` (:mod:`uavcal_jax.data.euroc_rig`). A camera's ``T_BS`` maps
camera points into ``B``; its optical axis (camera z) in ``Q`` is ``R_QB T_BS[:3, 2]``, and its
*pitch* is the angle of that axis below Q's x axis in Q's x-z plane, ``atan2(-z, x)`` (EuRoC's
cam0 also looks 1.5 degrees to the side; that yaw is kept). EuRoC's rig on EuRoC's mounting has
cam0 at :func:`rig_pitch_deg` = 19.76 degrees, cam1 at 18.96.

:func:`pitched_rig` turns the whole rig (both cameras, their baseline with them) about Q's y
axis through the body origin, so that cam0's pitch is the one asked for.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from uavcal_jax.data.euroc_rig import euroc_imu_mounting

__all__ = ["pitched_rig", "rig_pitch_deg"]


def rig_pitch_deg(T_BS: np.ndarray, R_QB: np.ndarray | None = None) -> float:
    """The pitch of camera ``T_BS`` (4, 4)'s optical axis below the quadrotor's forward axis,
    degrees (0 forward, 90 straight down), for the IMU mounting ``R_QB`` (3, 3; default
    EuRoC's)."""
    R_QB = euroc_imu_mounting() if R_QB is None else np.asarray(R_QB, dtype=np.float64)
    axis = R_QB @ np.asarray(T_BS, dtype=np.float64)[:3, 2]
    return float(np.degrees(np.arctan2(-axis[2], axis[0])))


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def pitched_rig(T_BS: Sequence[np.ndarray], pitch_deg: float | None,
                R_QB: np.ndarray | None = None) -> list[np.ndarray]:
    """The rig's camera extrinsics (each (4, 4) float64 ``T_BS``) turned together about the
    quadrotor's lateral (y) axis through the body origin so that the first camera's pitch
    (:func:`rig_pitch_deg`) is ``pitch_deg``; ``None`` returns copies unchanged.

    A positive turn pitches the optical axes down. The turn in the body frame is
    ``R_QB^T R_y(delta) R_QB``, applied on the left of every ``T_BS`` (rotation and
    translation), so the cameras keep their relative pose (the stereo baseline).
    """
    mats = [np.array(T, dtype=np.float64) for T in T_BS]
    if pitch_deg is None:
        return mats
    R_QB = euroc_imu_mounting() if R_QB is None else np.asarray(R_QB, dtype=np.float64)
    delta = np.radians(float(pitch_deg) - rig_pitch_deg(mats[0], R_QB))
    turn = np.eye(4)
    turn[:3, :3] = R_QB.T @ _rot_y(delta) @ R_QB
    return [turn @ T for T in mats]
