"""The world frame's one physical constant: gravity (world frame z up, SI units).

Every module that needs gravity (IMU synthesis, the trajectory planner, the IMU residual and
prediction, the VIO) reads it from here.
"""

from __future__ import annotations

__all__ = ["GRAVITY", "GRAVITY_W"]

#: Magnitude of gravity, m/s^2.
GRAVITY = 9.81
#: Gravity in the world frame (z up), m/s^2: an IMU at rest reads ``-GRAVITY_W`` rotated into
#: its frame.
GRAVITY_W = (0.0, 0.0, -GRAVITY)
