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
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["calibration_metrics", "metric_sums", "metrics_from_sums"]


def metric_sums(pred: jax.Array, target: jax.Array,
                weight: jax.Array | None = None) -> dict[str, jax.Array]:
    """Per-channel sums ``(C,)`` over windows of ``pred``/``target`` ``(B, C)``: ``tp``,
    ``fp``, ``fn``, ``sq_offset``, ``sq_magnitude`` and ``count``; ``weight (B,)`` (0/1)
    leaves padded windows out."""
    pred = pred.astype(jnp.float32)
    target = target.astype(jnp.float32)
    w = jnp.ones(pred.shape[0], jnp.float32) if weight is None else weight.astype(jnp.float32)
    w = w[:, None]
    pp, tp_ = pred > 0, target > 0
    return {
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
    ``sign_recall``, ``sign_f1``, ``magnitude_rmse``, ``offset_rmse`` overall (scalar) and,
    with the suffix ``_per_channel``, per channel ``(C,)``."""
    keys = ("tp", "fp", "fn", "sq_offset", "sq_magnitude", "count")
    per = _scores(*(sums[k] for k in keys))
    overall = _scores(*(jnp.sum(sums[k]) for k in keys))
    return {**overall, **{f"{k}_per_channel": v for k, v in per.items()}}


def calibration_metrics(pred: jax.Array, target: jax.Array,
                        weight: jax.Array | None = None) -> dict[str, jax.Array]:
    """Eq. 19-23 for one set of predictions ``(B, C)``; see :func:`metrics_from_sums`."""
    return metrics_from_sums(metric_sums(pred, target, weight))
