"""Offset estimators scored on recordings whose truth is known: the table of issue 20's
"unseen flights" and "real IMU" checks.

:func:`score_recordings` runs each named method (:mod:`uavcal_jax.pipeline.offset_estimators`)
on each recording (read once) through
:func:`~uavcal_jax.pipeline.predict_offset.predict_offset` (which hides the ground truth from
the method), scores it afterwards (:func:`~uavcal_jax.pipeline.predict_offset.score`) and
keeps one row per recording and method. :func:`pooled_scores` pools the rows of each method
over the recordings: the RMS error of every channel it estimates, per sensor (gyro rad/s,
accel m/s^2 pooled over their axes, :func:`uavcal_jax.calib.metrics.sensor_rmse`) and the
sign F1 of Avola et al. (eq. 19-21, :func:`uavcal_jax.calib.metrics.calibration_metrics`),
beside the same figures of *no correction* (the estimate 0: its error is the truth itself).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from uavcal_jax.calib.metrics import SENSORS, calibration_metrics, sensor_rmse
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS
from uavcal_jax.pipeline.predict_offset import known_offset, predict_offset, score

__all__ = ["NO_CORRECTION", "pooled_scores", "score_recordings"]

#: The name of the do-nothing baseline in :func:`pooled_scores`.
NO_CORRECTION = "no correction"


def score_recordings(recordings: Iterable[str | Path], methods: Iterable[str], *,
                     options: Mapping[str, Any] | None = None, inject=None,
                     progress: bool = False) -> list[dict]:
    """One row per recording and method: ``recording``, ``method``, ``channels``, ``offset``
    and ``true`` (in those channels), ``error``, ``sigma`` (a method's predicted standard
    deviation of its error, or ``None``) and ``seconds``. Recordings whose truth is unknown
    (no ``true``) are scored ``None``.

    Args:
        recordings: EuRoC/ASL folders (or bags) with ground truth, e.g. simulated ones.
        methods: registered method names.
        options: per method, its options (default: the method's defaults).
        inject: ``(6,)`` a constant added to every recording's IMU first (and to its truth),
            or ``None`` (:func:`~uavcal_jax.pipeline.predict_offset.predict_offset`).
        progress: progress bars for long work.
    """
    import time

    rows = []
    methods = list(methods)
    for recording in recordings:
        sequence, _ = read_sequence(recording)
        injected = known_offset(recorded_imu_offset(recording), inject)
        for method in methods:
            t0 = time.perf_counter()
            summary, estimate = predict_offset(sequence, method, (options or {}).get(method),
                                               inject=inject, progress=progress)
            summary.update(score(estimate, injected, sequence.ground_truth))
            rows.append({"recording": str(recording), "method": method,
                         "channels": summary["channels"], "offset": summary["offset"],
                         "true": summary["true"], "error": summary["error"],
                         "sigma": summary.get("sigma"),
                         "seconds": round(time.perf_counter() - t0, 2)})
    return rows


def _scores(pred: np.ndarray, true: np.ndarray, channels: list[str]) -> dict:
    metrics = calibration_metrics(jnp.asarray(pred, jnp.float32), jnp.asarray(true, jnp.float32))
    per_channel = np.sqrt(np.mean(np.square(pred - true), axis=0))
    return {"channels": channels,
            "rmse": {c: float(v) for c, v in zip(channels, per_channel, strict=True)},
            **{f"{s}_rmse": v for s, v in sensor_rmse(per_channel.tolist(), channels).items()},
            "sign_f1": float(metrics["sign_f1"]), "recordings": int(pred.shape[0])}


def pooled_scores(rows: list[dict]) -> dict[str, dict]:
    """Per method (in the rows' order), then :data:`NO_CORRECTION`: ``channels``, ``rmse``
    per channel, ``gyro_rmse`` / ``accel_rmse`` (``None`` for a sensor it does not estimate),
    ``sign_f1`` and ``recordings``, over the rows whose truth is known (and ``gyro_z_rms`` /
    ``accel_z_rms``, the root mean square of error / sigma over recordings and the sensor's
    channels, for a method whose rows all carry a predicted ``sigma``: 1 for a calibrated
    one). No correction is scored on every channel whose truth some method's row gives."""
    out: dict[str, dict] = {}
    truths: dict[str, dict[str, float]] = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        scored = [r for r in rows if r["method"] == method and r["true"] is not None]
        if not scored:
            continue
        channels = scored[0]["channels"]
        pred = np.array([r["offset"] for r in scored], np.float64)
        true = np.array([r["true"] for r in scored], np.float64)
        out[method] = _scores(pred, true, channels)
        if all(r.get("sigma") is not None for r in scored):  # the z-scores' spread
            # a channel a method could not determine (sigma null: infinite) is left out
            sigma = np.array([[np.nan if v is None else v for v in r["sigma"]]
                              for r in scored], np.float64)
            z = (pred - true) / sigma
            for sensor, head in SENSORS:
                pick = [j for j, c in enumerate(channels) if c.startswith(head)]
                finite = z[:, pick][np.isfinite(z[:, pick])]
                out[method][f"{sensor}_z_rms"] = (float(np.sqrt(np.mean(np.square(finite))))
                                                  if finite.size else None)
        for r in scored:
            truths.setdefault(r["recording"], {}).update(zip(r["channels"], r["true"],
                                                             strict=True))
    channels = [c for c in SIX_CHANNELS if all(c in t for t in truths.values())]
    if truths and channels:
        true = np.array([[t[c] for c in channels] for t in truths.values()], np.float64)
        out[NO_CORRECTION] = _scores(np.zeros_like(true), true, channels)
    return out
