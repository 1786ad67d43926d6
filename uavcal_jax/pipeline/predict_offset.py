"""A recording's IMU offset by any registered method, scored against the truth afterwards
(``uavcal calib predict``).

:func:`predict_offset` reads the recording, takes its ground truth away, adds ``inject`` (a
known miscalibration to try a method on) to its IMU, and hands that to the method
(:func:`~uavcal_jax.pipeline.offset_estimators.run_method`): no estimator sees the ground
truth or the simulator's record. Only then is the estimate scored (:func:`score`) against the
true offset under the estimate's label (:func:`uavcal_jax.data.true_offset.true_offset`):
the offsets known to be in the IMU (``sim_config.json``'s, written by ``uavcal simulate
--imu-offset``, plus ``inject``) and, for the ``total`` label, the ground truth's mean bias
over the span the estimate covers.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import numpy as np

from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sequence import GroundTruth, Sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.data.true_offset import true_offset
from uavcal_jax.errors import DataError
from uavcal_jax.imu.offset import add_offset
from uavcal_jax.pipeline.offset_estimate import OffsetEstimate
from uavcal_jax.pipeline.offset_estimators import DEFAULT_METHOD, configure_method, run_method

__all__ = ["predict_offset", "score", "with_imu_offset", "without_ground_truth"]


def without_ground_truth(sequence: Sequence) -> Sequence:
    """``sequence`` with no ground truth: what an offset estimator is given."""
    return dataclasses.replace(sequence, ground_truth=None)


def with_imu_offset(sequence: Sequence, offset) -> Sequence:
    """``sequence`` as recorded by an IMU with the extra constant ``offset`` (6,) (gyro rad/s,
    accel m/s^2; :func:`uavcal_jax.imu.offset.add_offset`), in float64; ``None``: as is.

    Raises:
        DataError: the sequence has no IMU, or ``offset`` is not 6 finite numbers.
    """
    if offset is None:
        return sequence
    offset = np.asarray(offset, np.float64).reshape(-1)
    if offset.shape != (6,) or not np.all(np.isfinite(offset)):
        raise DataError(f"an IMU offset is 6 finite numbers, got {offset.tolist()}")
    if sequence.imu is None:
        raise DataError("no IMU to add an offset to", sequence.root or sequence.name)
    imu = sequence.imu
    # 64-bit JAX: the default 32-bit arrays would round the samples to ~1e-6
    with jax.enable_x64(True):
        gyro, accel = add_offset(imu.gyro, imu.accel, offset)
        gyro, accel = np.asarray(gyro, np.float64), np.asarray(accel, np.float64)
    return dataclasses.replace(sequence, imu=dataclasses.replace(imu, gyro=gyro, accel=accel))


def score(estimate: OffsetEstimate, injected, ground_truth: GroundTruth | None) -> dict:
    """The estimate against the truth under its label.

    Args:
        estimate: an estimator's output.
        injected: ``(6,)`` the offsets known to be in the IMU (the simulator's and an
            injected one), or ``None`` for none known.
        ground_truth: the recording's, for the ``total`` label's sensor bias (its mean over
            ``estimate.span_ns``), or ``None``.

    Returns:
        JSON-ready ``true`` (in the estimate's channels), ``error`` (the median minus it) and
        ``rmse`` over the channels; all ``None`` when the truth is unknown.
    """
    truth = true_offset(estimate.label, injected, ground_truth, *estimate.span_ns)
    if truth is None:
        return {"true": None, "error": None, "rmse": None}
    true = truth[estimate.channel_index]
    error = np.asarray(estimate.median, np.float64) - true
    return {"true": true.tolist(), "error": error.tolist(),
            "rmse": float(np.sqrt(np.mean(np.square(error))))}


def predict_offset(recording: str | Path, method: str = DEFAULT_METHOD, options: Any = None,
                   *, inject=None, progress: bool = False) -> tuple[dict, OffsetEstimate]:
    """``(summary, estimate)``: method ``method``'s estimate of the IMU offset of
    ``recording`` (an EuRoC/ASL folder or a ROS bag, :func:`uavcal_jax.data.read.read_sequence`),
    scored against the truth when it is known.

    Args:
        recording: the recording's path.
        method: a registered method (:data:`~uavcal_jax.pipeline.offset_estimators.METHODS`).
        options: its options (:func:`~uavcal_jax.pipeline.offset_estimators.configure_method`;
            ``None``: its defaults).
        inject: ``(6,)`` added to the recorded IMU before estimating, or ``None``.
        progress: progress bars on stderr for long work (the VIO).

    Returns:
        ``summary`` (JSON-ready): ``method``, ``label``, ``sequence``, ``channels``,
        ``item`` (``window`` or ``frame``) and ``items``, the method's ``info``, ``offset``
        (the median, in ``channels``), ``per_window`` (each item's estimate; a VIO frame's for
        ``vio-bias``) with ``per_window_std`` and ``window_start_s`` (the items' times,
        seconds since the first frame), ``span_ns`` (the recording's span the estimate
        covers, ``OffsetEstimate.span_ns``), ``injected``, ``recorded`` (the simulator's
        offset), and ``true``, ``error``, ``rmse`` (:func:`score`; ``None`` when the truth
        is unknown).

    Raises:
        DataError: unreadable recording, unknown method, the method's own refusals.
    """
    if options is None:
        options = configure_method(method)
    sequence, _ = read_sequence(recording)
    blind = with_imu_offset(without_ground_truth(sequence), inject)
    estimate = run_method(method, blind, options, progress=progress)
    # the truth, only now: the simulator's record and the ground truth
    recorded = recorded_imu_offset(recording)
    injected = None
    if recorded is not None or inject is not None:
        injected = (np.zeros(6) if recorded is None else recorded) + (
            np.zeros(6) if inject is None else np.asarray(inject, np.float64))
    per_item = np.asarray(estimate.per_item, np.float64)
    summary = {
        "method": method, "label": estimate.label, "sequence": str(recording),
        "channels": list(estimate.channels), "item": estimate.item, "items": len(per_item),
        **estimate.info,
        "offset": np.asarray(estimate.median, np.float64).tolist(),
        "per_window_std": per_item.std(axis=0).tolist(),
        "per_window": per_item.tolist(),
        "window_start_s": np.asarray(estimate.item_t_s, np.float64).tolist(),
        "span_ns": [int(t) for t in estimate.span_ns],
        "injected": None if inject is None else np.asarray(inject, np.float64).tolist(),
        "recorded": None if recorded is None else recorded.tolist(),
        **score(estimate, injected, sequence.ground_truth),
    }
    return summary, estimate
