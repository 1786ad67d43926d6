"""``visual-ls``: the gyro's constant error from the camera's own rotations (VINS-Mono's
gyroscope-bias least squares).

The front end's tracks between consecutive left frames give the camera's relative rotation
(essential matrix, refined; :func:`uavcal_jax.vio.visual_rotation.relative_rotations`, cached
beside the recording); the gyro integrated over the same interval at full rate must agree
with it, and the constant that makes it agree best is the estimate
(:func:`uavcal_jax.vio.visual_gyro.gyro_bias_least_squares`). The rotations never see the
gyro, so the estimate is the whole constant error of the gyro (label ``total``). Relative
rotations say nothing of the accelerometer: the accel channels are not estimated (0 in
``offset``: nothing is subtracted there).

Measured on a 40 s simulated V2_01 flight with an injected offset: within 1.1e-4 rad/s of the
total per axis (:mod:`uavcal_jax.vio.visual_rotation` has the fits' measured reasons).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from uavcal_jax.config import apply_overrides
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.pipeline.offset_estimate import (
    SIX_CHANNELS,
    OffsetEstimate,
    OffsetMethod,
    check_sequence,
)
from uavcal_jax.pipeline.offset_uncertainty import recording_sigma
from uavcal_jax.vio.visual_gyro import VisualGyroConfig, visual_gyro_bias

__all__ = ["METHOD", "configure", "estimate"]

#: The channels this method estimates.
GYRO_CHANNELS = SIX_CHANNELS[:3]
#: Seconds per batch-means block of the frame pairs' estimates
#: (:func:`~uavcal_jax.pipeline.offset_uncertainty.recording_sigma`): a pair's rotation error
#: comes from its tracks, which the next pairs share for a second or so.
PAIR_BLOCK_S = 1.0
#: The sigma's calibration per gyro axis, measured by ``experiments/calib_uncertainty.py`` on
#: flights apart from those the tables judge it on (the 11 EuRoC trajectories from 40 s in,
#: 20 s each, seed 11: z-scores of RMS 0.93 unscaled, kept at 1).
SIGMA_SCALE = (1.0, 1.0, 1.0)


def configure(overrides: Iterable[str] = ()) -> VisualGyroConfig:
    """:class:`~uavcal_jax.vio.visual_gyro.VisualGyroConfig` with ``key=value``
    ``overrides`` (e.g. ``every=2``, ``frontend.max_corners=200``).

    Raises:
        uavcal_jax.config.ConfigError: an unknown key (named) or a bad value.
    """
    return apply_overrides(VisualGyroConfig(), list(overrides))


def estimate(sequence: Sequence, options: VisualGyroConfig = VisualGyroConfig(), *,  # noqa: B008
             progress: bool = False) -> OffsetEstimate:
    """The ``visual-ls`` estimate of ``sequence`` (a camera with its extrinsic, an IMU; no
    ground truth). Per item: the bias each frame interval alone implies.

    Raises:
        DataError: no IMU, too few usable frame pairs.
    """
    check_sequence(sequence)
    bias, per_interval, t_s = visual_gyro_bias(sequence, options, progress=progress)
    used = np.all(np.isfinite(per_interval), axis=1)
    first_ns = int(sequence.camera("cam0").t_ns[0])
    # the intervals' mid-points, absolute seconds; the span reaches half an interval further
    mid_ns = np.round(np.asarray(t_s)[used] * 1e9).astype(np.int64)
    half_ns = int(np.median(np.diff(sequence.camera("cam0").t_ns))) * options.every // 2
    span_ns = (int(mid_ns[0]) - half_ns, int(mid_ns[-1]) + half_ns)
    offset = np.zeros(6)
    offset[:3] = bias
    item_t_s = (mid_ns - first_ns) * 1e-9
    sigma = recording_sigma(per_interval[used], item_t_s, PAIR_BLOCK_S,
                            scale=np.array(SIGMA_SCALE))
    return OffsetEstimate(
        offset=offset, channels=GYRO_CHANNELS, median=np.asarray(bias, np.float64),
        per_item=per_interval[used], item_t_s=item_t_s, item="frame pair",
        span_ns=span_ns, label="total", settings=options,
        info={"intervals": int(per_interval.shape[0]), "intervals_used": int(used.sum())},
        sigma=np.maximum(sigma, np.finfo(np.float64).tiny))


METHOD = OffsetMethod(
    name="visual-ls", configure=configure, estimate=estimate,
    summary="gyro only: VINS-Mono's gyro-bias least squares of the full-rate gyro against the "
            "camera's frame-to-frame rotations (essential matrix on the front end's tracks, "
            "cached beside the recording; --set every=K, min_tracks=N, frontend.KEY=VALUE)")
