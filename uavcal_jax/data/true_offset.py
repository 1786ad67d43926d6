"""The true constant error of a recording's IMU: what a user should subtract.

Two parts make it up:

- the **injected offset**: a constant added to the written IMU (``uavcal simulate
  --imu-offset``, recorded in ``sim_config.json``; or an offset a caller adds itself);
- the **sensor's own bias** over the span in question: the mean of the ground truth's bias
  columns (``GroundTruth.bias_gyro`` / ``bias_accel``; EuRoC and the simulator write them;
  a TUM file has none).

The *label* of a calibration names which of the two counts (:data:`LABELS`): ``injected``
(the paper's reproduction: the offset alone) or ``total`` (offset plus sensor bias: the
constant to subtract). Nothing here is an estimator: these are ground-truth figures, for
labels and scores only.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.data.sequence import GroundTruth

__all__ = ["LABELS", "sensor_bias", "true_offset"]

#: What a calibration's label is: the injected offset alone, or offset plus the sensor's own
#: bias (the total constant error, what to subtract from the IMU).
LABELS = ("injected", "total")


def sensor_bias(ground_truth: GroundTruth | None, t0_ns: int | None = None,
                t1_ns: int | None = None) -> np.ndarray | None:
    """The ``(6,)`` mean ground-truth IMU bias (gyro rad/s xyz, accel m/s^2 xyz) over
    ``[t0_ns, t1_ns]`` (default the whole ground truth); ``None`` when the ground truth has no
    bias columns, or no sample falls in the span."""
    if ground_truth is None or ground_truth.bias_gyro is None or ground_truth.bias_accel is None:
        return None
    t = np.asarray(ground_truth.t_ns, np.int64)
    keep = np.ones(t.shape, bool)
    if t0_ns is not None:
        keep &= t >= int(t0_ns)
    if t1_ns is not None:
        keep &= t <= int(t1_ns)
    if not keep.any():
        return None
    bias = np.concatenate([np.asarray(ground_truth.bias_gyro, np.float64)[keep],
                           np.asarray(ground_truth.bias_accel, np.float64)[keep]], axis=1)
    return bias.mean(axis=0)


def true_offset(label: str, injected: np.ndarray | None, ground_truth: GroundTruth | None,
                t0_ns: int | None = None, t1_ns: int | None = None) -> np.ndarray | None:
    """The ``(6,)`` true constant error under ``label`` (see :data:`LABELS`), or ``None`` when
    the inputs cannot determine it.

    Args:
        label: ``"injected"`` or ``"total"``.
        injected: ``(6,)`` the offset added to the IMU, or ``None`` for none known.
        ground_truth: the recording's ground truth (its bias columns), for ``total``.
        t0_ns, t1_ns: the span the sensor bias is averaged over (default all of it).

    Returns:
        ``injected`` for ``"injected"`` (``None`` when unknown); for ``"total"``,
        ``injected`` (zeros when ``None``) plus :func:`sensor_bias`, ``None`` when the ground
        truth has no bias columns.
    """
    if label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    offset = None if injected is None else np.asarray(injected, np.float64).reshape(6)
    if label == "injected":
        return offset
    bias = sensor_bias(ground_truth, t0_ns, t1_ns)
    if bias is None:
        return None
    return bias if offset is None else offset + bias
