"""The accelerometer's constant error over one window, from a metric visual trajectory: the
calibrator's metric start (issue 43; ``WindowConfig.accel_start="alignment"``).

Per window: VINS-Mono's visual-inertial alignment with the accelerometer bias
(:func:`uavcal_jax.imu.accel_alignment.align_accel_bias`) between the stereo VIO's tracked
poses inside the window and the IMU preintegrated between them: velocities, gravity and the
bias solved together, the scale given by stereo. A window that hardly turns cannot tell the
bias across gravity from its tilt; there the solution leans on the alignment's zero-mean
prior and its standard deviation says so (near the prior's 0.1 m/s^2), which the model reads
beside the estimate.

Training injects offsets into clean recordings, so the start must move as the alignment of
the injected IMU would. Preintegration is linear in the accelerometer's samples and the
rotations the gyro chains are unchanged when the gyro offset is removed with the VIO's bias
(which holds it), so a constant accelerometer offset ``d`` moves the solution by
``response @ d``: the identity where the window determines the bias, less where the prior
holds it (measured here by re-solving with a unit offset on each axis).

Frames: the VIO's world (z up) and the body (IMU) frame; m/s^2.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from uavcal_jax.errors import DataError
from uavcal_jax.imu.accel_alignment import align_accel_bias
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise

__all__ = ["ANCHOR_S", "NODE_SPACING_S", "PRIOR_STD", "WindowAlignment",
           "window_accel_starts"]

#: Seconds between the alignment's nodes inside a window (a 2 s window holds 8 intervals).
NODE_SPACING_S = 0.25
#: The alignment's zero-mean prior on the bias, m/s^2 per axis (the sensor's turn-on spread;
#: :func:`~uavcal_jax.imu.accel_alignment.align_accel_bias`'s default).
PRIOR_STD = 0.1
#: The offset the response is measured with, m/s^2 (the solution is linear in it).
_PROBE = 0.1
#: Seconds within which windows' alignment spans (longer than the windows) share one solve.
ANCHOR_S = 1.0


class WindowAlignment(NamedTuple):
    """Per window: ``start (W, 3)`` the bias estimate (0 where no alignment could be made),
    ``response (W, 3, 3)`` its change per unit of a constant accelerometer offset (0 there),
    ``std (W, 3)`` its standard deviation (:data:`PRIOR_STD` there), all m/s^2, body frame."""

    start: np.ndarray
    response: np.ndarray
    std: np.ndarray


def _solve(t_ns, position, rotation, imu_t_ns, gyro, accel, bias_gyro, noise):
    out = align_accel_bias(t_ns, position, rotation, imu_t_ns, gyro, accel, bias_gyro,
                           node_spacing_s=NODE_SPACING_S, prior_std=PRIOR_STD, noise=noise)
    return out.bias_accel, out.bias_std


def window_accel_starts(poses, imu_t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                        starts_ns: np.ndarray, duration_ns: int, span_ns: int | None = None,
                        noise: ImuNoise = EUROC_ADIS16448) -> WindowAlignment:
    """The alignment of every window ``[s, s + duration_ns)`` (module docstring).

    Args:
        poses: the VIO's trajectory of the recording (``t_ns``, ``position``, ``rotation``,
            ``bias_gyro``, ``tracked``: :class:`uavcal_jax.vio.pose_cache.VioPoses`).
        imu_t_ns, gyro, accel: the recorded IMU (N,), (N, 3), (N, 3).
        starts_ns: (W,) window starts; duration_ns: their length.
        span_ns: the alignment's span, centred on the window (``None``: the window itself).
            The bias across gravity shows only through turns, which a 2 s window rarely
            holds (measured on a 20 s MH_04 flight: a 2 s window's alignment moves 0.0-0.1 of
            an offset across gravity, a 10 s one 0.5); a longer span reads the flight around
            the window. Windows whose spans start within :data:`ANCHOR_S` of each other
            share one solve.
        noise: the IMU's noise model (the residuals' weights).
    """
    starts_ns = np.asarray(starts_ns, np.int64)
    w = starts_ns.size
    start, response = np.zeros((w, 3)), np.zeros((w, 3, 3))
    std = np.full((w, 3), PRIOR_STD)
    t = np.asarray(poses.t_ns, np.int64)
    good = np.asarray(poses.tracked, bool)
    imu_t_ns = np.asarray(imu_t_ns, np.int64)
    span_ns = duration_ns if span_ns is None else int(span_ns)
    lo_ns = starts_ns + (duration_ns - span_ns) // 2
    if t.size:  # a span past the recording's ends is moved inside (as far as it fits)
        lo_ns = np.clip(lo_ns, t[0], max(t[0], t[-1] - span_ns))
    anchor_ns = int(ANCHOR_S * 1e9)
    solved: dict[int, tuple] = {}
    for k, s in enumerate(lo_ns):
        key = int(s // anchor_ns) if span_ns > duration_ns else k
        if key in solved:
            if solved[key] is not None:
                start[k], response[k], std[k] = solved[key]
            continue
        solved[key] = None
        pick = np.flatnonzero(good & (t >= s) & (t < s + span_ns))
        if pick.size < 2:
            continue
        lo, hi = np.searchsorted(imu_t_ns, [t[pick[0]], t[pick[-1]]])
        part = slice(max(lo - 1, 0), hi + 1)
        args = (t[pick], poses.position[pick], poses.rotation[pick], imu_t_ns[part],
                gyro[part])
        bias_gyro = np.median(poses.bias_gyro[pick], axis=0)
        try:
            b0, sd = _solve(*args, accel[part], bias_gyro, noise)
        except DataError:  # too few nodes in the window's tracked stretch
            continue
        start[k], std[k] = b0, sd
        for axis in range(3):
            shifted = accel[part] + _PROBE * np.eye(3)[axis]
            response[k, :, axis] = (_solve(*args, shifted, bias_gyro, noise)[0] - b0) / _PROBE
        solved[key] = (start[k], response[k], std[k])
    return WindowAlignment(start, response, std)
