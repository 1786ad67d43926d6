"""The check of a window's start while moving: the frames since a window opened (or since a
reset), their stereo depths and IMU intervals, aligned by
:func:`~uavcal_jax.vio.motion_init.initialize_moving` once ``init_frames`` of them are in.

The estimator (:class:`~uavcal_jax.vio.estimator.StereoVio`) holds one :class:`StartCheck`
while a start is unconfirmed: after the first start (levelled by the accelerometer and at
rest, an assumption that is wrong while the body accelerates) it compares the solved window
with the alignment (:meth:`StartCheck.disagrees`) and re-opens the window at the aligned state
when they differ; after a reset it coasts until the frames align and opens there.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.frontend import FrameFeatures
from uavcal_jax.vio.imu_slice import IMU_GAP_PERIODS, ImuStream
from uavcal_jax.vio.motion_init import initialize_moving

__all__ = ["StartCheck"]


class StartCheck:
    """The last ``config.init_frames`` consecutive frames and the tries to align them.

    Args:
        imu: the estimator's IMU stream (raw intervals between the frames).
        T_BC0: (4, 4) left camera to body.
        config: ``init_frames``, ``min_init_landmarks``, ``init_tilt_deg``, ``init_velocity``.
    """

    def __init__(self, imu: ImuStream, T_BC0: np.ndarray, config: VioConfig):
        self.imu, self.T_BC0, self.config = imu, T_BC0, config
        # (t_ns, features, stereo depths, IMU interval from the frame before)
        self.frames: list[tuple] = []
        self.tries = 0

    @property
    def exhausted(self) -> bool:
        """More than ``3 * init_frames`` tries: the check gives up."""
        return self.tries > 3 * self.config.init_frames

    def add(self, t_ns: int, feats: FrameFeatures, depths: tuple) -> None:
        """Keep the frame (with its stereo ``depths``, :func:`~uavcal_jax.vio.slots.
        stereo_depths`, and the IMU interval before it); an IMU gap or a frame with fewer than
        ``min_init_landmarks`` usable matches restarts the stretch."""
        buf = self.frames
        iv = None
        if buf:
            iv = self.imu.raw(buf[-1][0], t_ns)
            if iv is None or iv.dt.max() > IMU_GAP_PERIODS * self.imu.period:
                buf.clear()
        if int(np.sum(depths[1])) < self.config.min_init_landmarks:
            buf.clear()  # the odometry needs every frame of the stretch
            return
        buf.append((t_ns, feats, depths, iv if buf else None))
        del buf[:-self.config.init_frames]

    def align(self, ref: BodyState) -> BodyState | None:
        """The state at the newest kept frame from the frames' stereo odometry and IMU:
        aligned gravity and velocity, ``ref``'s position and heading, zero biases (the window
        estimates them; after a failure the old ones are suspect). ``None`` while the frames
        are too few or do not align (the oldest is then dropped). Counts the try."""
        buf = self.frames
        self.tries += 1
        if len(buf) < self.config.init_frames:
            return None
        rows = [(b[3].dt, b[3].gyro, b[3].accel) for b in buf[1:]]
        init = initialize_moving([b[1] for b in buf], [b[2] for b in buf], rows, self.T_BC0,
                                 ref.rotation)
        if init is None:
            del buf[0]
            return None
        return BodyState(ref.t_ns, init.rotation, ref.position.copy(), init.velocity,
                         np.zeros(3), np.zeros(3))

    def disagrees(self, start: BodyState, solved: BodyState) -> bool:
        """The aligned ``start`` differs from the ``solved`` window's state by more than
        ``init_tilt_deg`` in tilt or ``init_velocity`` in velocity."""
        cos = np.clip(start.rotation[2] @ solved.rotation[2], -1.0, 1.0)
        dv = float(np.linalg.norm(start.velocity - solved.velocity))
        return bool(np.degrees(np.arccos(cos)) > self.config.init_tilt_deg
                    or dv > self.config.init_velocity)
