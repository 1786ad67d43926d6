"""The estimator's view of the IMU stream: the samples between two frames as a padded window
row (:class:`ImuSlice`, a typed result: samples, or why there are none), the gyro rotation
that seeds the optical flow, and the accelerometer mean that levels the first keyframe.

Padding: a frame-to-frame interval is padded to a short row of :data:`FRAME_SAMPLES` (the
per-frame preintegration scans it), a longer one (dropped frames) to the window's full row of
``capacity`` samples; :meth:`ImuStream.full_row` widens a short row for the window, whose
merges need every row the same length. NumPy, float64; times in ns.
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import ImuData
from uavcal_jax.errors import DataError
from uavcal_jax.imu import ImuInterval, interval_samples
from uavcal_jax.vio.window import ImuSamples

__all__ = ["FRAME_SAMPLES", "IMU_GAP_PERIODS", "MIN_LEVEL_SAMPLES", "ImuGap", "ImuSlice",
           "ImuStream"]

#: IMU samples further apart than this many nominal periods are a gap the window cannot bridge.
IMU_GAP_PERIODS = 5.0
#: Padded row of one frame-to-frame interval (20 Hz frames, 200 Hz IMU: 11 samples).
FRAME_SAMPLES = 32
#: Fewest accelerometer samples averaged to level the first keyframe.
MIN_LEVEL_SAMPLES = 3


class ImuGap(enum.Enum):
    """Why an interval has no usable samples; the value is the estimate's ``reason``."""

    NO_IMU = "no_imu"  # the interval is not inside the stream
    GAP = "imu_gap"  # samples too far apart, or more than a window row holds


@dataclasses.dataclass(frozen=True)
class ImuSlice:
    """The samples of one interval, or why there are none.

    Attributes:
        samples: :class:`~uavcal_jax.vio.window.ImuSamples` row (S,) (``None`` with a gap).
        gap: ``None`` when the samples are usable, else the :class:`ImuGap`.
    """

    samples: ImuSamples | None
    gap: ImuGap | None = None


class ImuStream:
    """Read-only slices of one IMU stream (safe to share between the front-end and back-end
    threads).

    Args:
        imu: the whole stream (samples already corrected for any known offset).
        rate_hz: its nominal rate.  capacity: samples in the window's row (``imu_samples``).
    """

    def __init__(self, imu: ImuData, rate_hz: float, capacity: int):
        self.data = imu
        self.period = 1.0 / rate_hz
        self.capacity = capacity

    def raw(self, t0_ns: int, t1_ns: int) -> ImuInterval | None:
        """:func:`~uavcal_jax.imu.interval_samples` of ``[t0, t1]`` on the few samples around it
        (validating the whole stream every frame would cost more than integrating), or
        ``None`` when the interval is not inside the stream."""
        t = self.data.t_ns
        lo = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(t, t1_ns, side="left")) + 1, len(t))
        try:
            return interval_samples(t[lo:hi], self.data.gyro[lo:hi], self.data.accel[lo:hi],
                                    t0_ns, t1_ns)
        except DataError:
            return None

    def slice(self, t0_ns: int, t1_ns: int) -> ImuSlice:
        """Samples of ``[t0, t1]`` padded to :data:`FRAME_SAMPLES` (or to ``capacity`` when
        longer), or the gap that prevents it."""
        iv = self.raw(t0_ns, t1_ns)
        if iv is None:
            return ImuSlice(None, ImuGap.NO_IMU)
        n = len(iv.dt)
        if iv.dt.max() > IMU_GAP_PERIODS * self.period or n > self.capacity:
            return ImuSlice(None, ImuGap.GAP)
        S = FRAME_SAMPLES if n <= FRAME_SAMPLES else self.capacity
        dt = np.full(S, self.period)
        gyro = np.zeros((S, 3))
        accel = np.zeros((S, 3))
        mask = np.zeros(S, bool)
        dt[:n], gyro[:n], accel[:n], mask[:n] = iv.dt, iv.gyro, iv.accel, True
        return ImuSlice(ImuSamples(dt, gyro, accel, mask))

    def full_row(self, row: ImuSamples) -> ImuSamples:
        """``row`` padded to ``capacity`` (what merging intervals needs)."""
        S = self.capacity
        n = row.dt.shape[0]
        if n == S:
            return row
        return ImuSamples(np.pad(row.dt, (0, S - n), constant_values=self.period),
                          np.pad(row.gyro, ((0, S - n), (0, 0))),
                          np.pad(row.accel, ((0, S - n), (0, 0))),
                          np.pad(row.mask, (0, S - n)))

    def gyro_rotation(self, t0_ns: int, t1_ns: int, bias_gyro: np.ndarray) -> np.ndarray | None:
        """(3, 3) body rotation from ``t0`` to ``t1`` (maps body vectors at ``t1`` to the body
        at ``t0``) of the gyro corrected by ``bias_gyro`` (3,) rad/s; ``None`` outside the
        stream."""
        iv = self.raw(t0_ns, t1_ns)
        if iv is None:
            return None
        R = np.eye(3)
        for dt, w in zip(iv.dt, iv.gyro - bias_gyro, strict=True):
            R = R @ Rotation.from_rotvec(w * dt).as_matrix()
        return R

    def accel_mean(self, t_ns: int, seconds: float) -> np.ndarray:
        """(3,) m/s^2, the accelerometer averaged over ``seconds`` before ``t_ns`` (or over the
        samples nearest ``t_ns`` when fewer than :data:`MIN_LEVEL_SAMPLES` fall there)."""
        t = self.data.t_ns
        sel = (t <= t_ns) & (t >= t_ns - int(seconds * 1e9))
        if sel.sum() < MIN_LEVEL_SAMPLES:
            sel = np.argsort(np.abs(t - t_ns))[:max(MIN_LEVEL_SAMPLES,
                                                    int(seconds / self.period))]
        return np.mean(self.data.accel[sel], axis=0)
