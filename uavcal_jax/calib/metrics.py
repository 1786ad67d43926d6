"""Evaluation metrics of Avola et al. (2023), eq. 19-23, per channel and overall.

Sign classification (eq. 19-21) treats "the offset of a channel is positive" as the
positive class: for true offsets ``o`` and predictions ``o_hat``,
``TP = #(o_hat > 0 and o > 0)``, ``FP = #(o_hat > 0 and o <= 0)``,
``FN = #(o_hat <= 0 and o > 0)``; precision ``TP / (TP + FP)``, recall ``TP / (TP + FN)``,
``F1 = 2 TP / (2 TP + FP + FN)`` (0 when there are no positives at all). Magnitude RMSE
(eq. 22) is ``sqrt(mean((|o_hat| - |o|)^2))`` and offset RMSE (eq. 23)
``sqrt(mean((o_hat - o)^2))``.

"Per channel" counts over windows for each channel ``(C,)``; "overall" pools every window and
channel (micro average, the same sums). Metrics are computed from sums so that batches can
be accumulated: :func:`metric_sums` per batch, add them, :func:`metrics_from_sums`.

"Per sensor" (:func:`sensor_rmse`, :func:`seed_summary`) reads those metrics back per seed
(plain lists, as :func:`uavcal_jax.calib.loop.evaluate` returns them) and splits the
channels by name: gyro (``g*``, rad/s) and accel (``a*``, m/s^2).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["SENSORS", "calibration_metrics", "metric_sums", "metrics_from_sums", "seed_summary",
           "sensor_rmse", "sign_f1_without"]

#: ``(sensor, channel-name prefix)``: the names of :func:`uavcal_jax.calib.predict.channel_names`.
SENSORS = (("gyro", "g"), ("accel", "a"))


def metric_sums(pred: jax.Array, target: jax.Array, weight: jax.Array | None = None,
                log_sigma: jax.Array | None = None) -> dict[str, jax.Array]:
    """Per-channel sums ``(C,)`` over windows of ``pred``/``target`` ``(B, C)``: ``tp``,
    ``fp``, ``fn``, ``sq_offset``, ``sq_magnitude`` and ``count``; ``weight (B,)`` (0/1)
    leaves padded windows out. With a predicted uncertainty ``log_sigma (B, C)``
    (``ModelConfig.variance``) also ``sq_z`` (the squared z-scores ``(pred - target) /
    sigma``) and ``sq_sigma``."""
    pred = pred.astype(jnp.float32)
    target = target.astype(jnp.float32)
    w = jnp.ones(pred.shape[0], jnp.float32) if weight is None else weight.astype(jnp.float32)
    w = w[:, None]
    pp, tp_ = pred > 0, target > 0
    spread = {}
    if log_sigma is not None:
        log_sigma = log_sigma.astype(jnp.float32)
        spread = {"sq_z": jnp.sum(w * jnp.square((pred - target) * jnp.exp(-log_sigma)), axis=0),
                  "sq_sigma": jnp.sum(w * jnp.exp(2.0 * log_sigma), axis=0)}
    return {**spread,
        "tp": jnp.sum(w * (pp & tp_), axis=0),
        "fp": jnp.sum(w * (pp & ~tp_), axis=0),
        "fn": jnp.sum(w * (~pp & tp_), axis=0),
        "sq_offset": jnp.sum(w * jnp.square(pred - target), axis=0),
        "sq_magnitude": jnp.sum(w * jnp.square(jnp.abs(pred) - jnp.abs(target)), axis=0),
        "count": jnp.sum(w * jnp.ones_like(pred), axis=0),
    }


def _ratio(num, den):
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _scores(tp, fp, fn, sq_o, sq_m, count):
    return {
        "sign_precision": _ratio(tp, tp + fp),
        "sign_recall": _ratio(tp, tp + fn),
        "sign_f1": _ratio(2 * tp, 2 * tp + fp + fn),
        "magnitude_rmse": jnp.sqrt(_ratio(sq_m, count)),
        "offset_rmse": jnp.sqrt(_ratio(sq_o, count)),
    }


def metrics_from_sums(sums: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Scores from (accumulated) :func:`metric_sums`: each of ``sign_precision``,
    ``sign_recall``, ``sign_f1``, ``magnitude_rmse``, ``offset_rmse`` (and, with an
    uncertainty, ``z_rms``: the z-scores' spread, 1 for a calibrated one; ``sigma_rms``: the
    predicted sigma's root mean square, beside ``offset_rmse``) overall (scalar) and, with
    the suffix ``_per_channel``, per channel ``(C,)``."""
    keys = ("tp", "fp", "fn", "sq_offset", "sq_magnitude", "count")
    per = _scores(*(sums[k] for k in keys))
    overall = _scores(*(jnp.sum(sums[k]) for k in keys))
    if "sq_z" in sums:  # a predicted uncertainty: calibrated when z_rms is 1
        for key, name in (("sq_z", "z_rms"), ("sq_sigma", "sigma_rms")):
            per[name] = jnp.sqrt(_ratio(sums[key], sums["count"]))
            overall[name] = jnp.sqrt(_ratio(jnp.sum(sums[key]), jnp.sum(sums["count"])))
    counts = {f"{k}_per_channel": sums[k] for k in ("tp", "fp", "fn")}
    return {**overall, **{f"{k}_per_channel": v for k, v in per.items()}, **counts}


def sign_f1_without(metrics: dict, channels: Sequence[str], drop: Sequence[str]) -> float:
    """The overall sign F1 (eq. 21, micro average) of one seed's :func:`metrics_from_sums`
    (plain values) with the channels named in ``drop`` left out: e.g. ``ax``, whose sign
    never changes under the paper's protocol (gravity's reaction), which inflates F1."""
    keep = np.array([c not in drop for c in channels])
    tp, fp, fn = (float(np.sum(np.asarray(metrics[f"{k}_per_channel"])[keep]))
                  for k in ("tp", "fp", "fn"))
    return 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn > 0 else 0.0


def calibration_metrics(pred: jax.Array, target: jax.Array,
                        weight: jax.Array | None = None) -> dict[str, jax.Array]:
    """Eq. 19-23 for one set of predictions ``(B, C)``; see :func:`metrics_from_sums`."""
    return metrics_from_sums(metric_sums(pred, target, weight))


def sensor_rmse(offset_rmse_per_channel, channels: Sequence[str]) -> dict[str, float | None]:
    """Offset RMSE of each sensor of :data:`SENSORS` (gyro rad/s, accel m/s^2) from one seed's
    ``offset_rmse_per_channel (C,)`` named by ``channels``: the root mean square of its
    channels' RMSEs (every channel counts the same windows, so this pools them); ``None`` for
    a sensor without channels."""
    per_channel = np.asarray(offset_rmse_per_channel)
    out: dict[str, float | None] = {}
    for sensor, head in SENSORS:
        pick = [j for j, c in enumerate(channels) if c.startswith(head)]
        out[sensor] = float(np.sqrt(np.mean(np.square(per_channel[pick])))) if pick else None
    return out


def seed_summary(per_seed: Sequence[dict], channels: Sequence[str]) -> dict:
    """Headline numbers of one method on one trial, averaged over seeds, from eq. 19-23
    metrics (one :func:`metrics_from_sums` dict of plain values per seed): ``sign_f1`` and
    ``offset_rmse`` (every channel pooled), ``sign_f1_without_ax`` (:func:`sign_f1_without`;
    ``None`` without an ``ax`` channel), ``offset_rmse_per_channel`` and
    ``sign_f1_per_channel`` (lists of ``C``), and ``gyro_rmse`` / ``accel_rmse``
    (:func:`sensor_rmse` per seed, then the mean; ``None`` without that sensor)."""
    def avg(key):
        return np.mean([np.asarray(m[key], np.float64) for m in per_seed], axis=0)

    out = {"sign_f1": float(avg("sign_f1")), "offset_rmse": float(avg("offset_rmse")),
           "sign_f1_without_ax": (float(np.mean([sign_f1_without(m, channels, ("ax",))
                                                 for m in per_seed]))
                                  if "ax" in channels and "tp_per_channel" in per_seed[0]
                                  else None),
           "offset_rmse_per_channel": avg("offset_rmse_per_channel").tolist(),
           "sign_f1_per_channel": avg("sign_f1_per_channel").tolist()}
    per_sensor = [sensor_rmse(m["offset_rmse_per_channel"], channels) for m in per_seed]
    for sensor, _ in SENSORS:
        values = [r[sensor] for r in per_sensor]
        out[f"{sensor}_rmse"] = None if values[0] is None else float(np.mean(values))
    return out
