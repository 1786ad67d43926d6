"""A recording's IMU offset by any registered method (``uavcal calib predict``, ``uavcal
run``), and the one function that scores an estimate against the truth.

:func:`predict_offset` takes a recording already read (a
:class:`~uavcal_jax.data.sequence.Sequence`), takes its ground truth away, adds ``inject`` (a
known miscalibration to try a method on) to its IMU, and hands that to the method
(:func:`~uavcal_jax.pipeline.offset_estimators.run_method`): no estimator sees the ground
truth or the simulator's record, and none is given a path to read the recording again (the
sequence's ``root`` only names where a method may cache what it computed from the frames).
The caller, which holds the truth, scores the estimate afterwards (:func:`score`) against the
true offset under the estimate's label (:func:`uavcal_jax.data.true_offset.true_offset`):
the offsets known to be in the IMU (:func:`known_offset`: ``sim_config.json``'s, written by
``uavcal simulate --imu-offset``, plus ``inject``) and, for the ``total`` label, the ground
truth's mean bias over the span the estimate covers.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from uavcal_jax.data.imu_coverage import check_imu_covers
from uavcal_jax.data.sequence import GroundTruth, Sequence
from uavcal_jax.data.true_offset import true_offset
from uavcal_jax.errors import DataError
from uavcal_jax.imu.offset import add_offset
from uavcal_jax.pipeline.offset_estimate import OffsetEstimate
from uavcal_jax.pipeline.offset_estimators import DEFAULT_METHOD, configure_method, run_method

__all__ = ["known_offset", "predict_offset", "score", "with_imu_offset", "without_ground_truth"]


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


def score(estimate: OffsetEstimate, injected, ground_truth: GroundTruth | None, *,
          all_channels: bool = False) -> dict:
    """The estimate against the truth under its label: the one place an offset is scored.

    Args:
        estimate: an estimator's output.
        injected: ``(6,)`` the offsets known to be in the IMU (the simulator's and an
            injected one, :func:`known_offset`), or ``None`` for none known.
        ground_truth: the recording's, for the ``total`` label's sensor bias (its mean over
            ``estimate.span_ns``), or ``None``.
        all_channels: score ``estimate.offset`` over all six channels (0 where the method
            estimates nothing: what an IMU corrected by it keeps), not ``estimate.median``
            in its channels.

    Returns:
        JSON-ready ``true`` (in the estimate's channels, or all six), ``error`` (the estimate
        minus it) and ``rmse`` over those channels; all ``None`` when the truth is unknown.
    """
    truth = true_offset(estimate.label, injected, ground_truth, *estimate.span_ns)
    if truth is None:
        return {"true": None, "error": None, "rmse": None}
    if all_channels:
        true, value = truth, np.asarray(estimate.offset, np.float64)
    else:
        true = truth[estimate.channel_index]
        value = np.asarray(estimate.median, np.float64)
    error = value - true
    return {"true": true.tolist(), "error": error.tolist(),
            "rmse": float(np.sqrt(np.mean(np.square(error))))}


def known_offset(recorded, inject) -> np.ndarray | None:
    """``(6,)`` the offsets known to be in an IMU: the simulator's ``recorded`` one
    (:func:`uavcal_jax.data.sim_config.recorded_imu_offset`) plus an ``inject``-ed one, either
    ``None``; ``None`` when neither is known (:func:`score`'s ``injected``)."""
    if recorded is None and inject is None:
        return None
    return (np.zeros(6) if recorded is None else np.asarray(recorded, np.float64)) + (
        np.zeros(6) if inject is None else np.asarray(inject, np.float64))


def predict_offset(sequence: Sequence, method: str = DEFAULT_METHOD, options: Any = None,
                   *, inject=None, progress: bool = False) -> tuple[dict, OffsetEstimate]:
    """``(summary, estimate)``: method ``method``'s estimate of the IMU offset of
    ``sequence`` (read once by the caller, :func:`uavcal_jax.data.read.read_sequence`), given
    to the method without its ground truth (:func:`without_ground_truth`) and with ``inject``
    added to its IMU. Nothing is scored here: the caller, which holds the truth sources,
    adds :func:`score`'s figures (``summary.update(score(estimate, known_offset(recorded,
    inject), sequence.ground_truth))``).

    Args:
        sequence: the recording.
        method: a registered method (:data:`~uavcal_jax.pipeline.offset_estimators.METHODS`).
        options: its options (:func:`~uavcal_jax.pipeline.offset_estimators.configure_method`;
            ``None``: its defaults).
        inject: ``(6,)`` added to the recorded IMU before estimating, or ``None``.
        progress: progress bars on stderr for long work (the VIO).

    Returns:
        ``summary`` (JSON-ready): ``method``, ``label``, ``sequence`` (the recording's
        folder, else its name), ``channels``, ``item`` (``window`` or ``frame``) and
        ``items``, the method's ``info``, ``offset`` (the median, in ``channels``),
        ``sigma`` (the estimate's standard deviation in ``channels``,
        :attr:`~uavcal_jax.pipeline.offset_estimate.OffsetEstimate.sigma`; ``None`` when the
        method gives none; a channel it cannot determine is ``null``),
        ``per_window`` (each item's estimate; a VIO frame's for ``vio-bias``) with
        ``per_window_std`` and ``window_start_s`` (the items' times, seconds since the first
        frame), ``span_ns`` (the recording's span the estimate covers,
        ``OffsetEstimate.span_ns``) and ``injected``.

    Raises:
        DataError: unknown method, an IMU that does not cover the left camera's frames
            (:func:`~uavcal_jax.data.imu_coverage.check_imu_covers`), the method's own
            refusals.
    """
    if options is None:
        options = configure_method(method)
    if "cam0" in sequence.cameras:  # the frames an estimator integrates the IMU between
        check_imu_covers(sequence)
    blind = with_imu_offset(without_ground_truth(sequence), inject)
    estimate = run_method(method, blind, options, progress=progress)
    per_item = np.asarray(estimate.per_item, np.float64)
    summary = {
        "method": method, "label": estimate.label,
        "sequence": str(sequence.root if sequence.root is not None else sequence.name),
        "channels": list(estimate.channels), "item": estimate.item, "items": len(per_item),
        **estimate.info,
        "offset": np.asarray(estimate.median, np.float64).tolist(),
        "sigma": None if estimate.sigma is None else [
            float(v) if np.isfinite(v) else None for v in estimate.sigma],
        "per_window_std": per_item.std(axis=0).tolist(),
        "per_window": per_item.tolist(),
        "window_start_s": np.asarray(estimate.item_t_s, np.float64).tolist(),
        "span_ns": [int(t) for t in estimate.span_ns],
        "injected": None if inject is None else np.asarray(inject, np.float64).tolist(),
    }
    return summary, estimate
