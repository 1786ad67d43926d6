"""Box operations in pure ``jax.numpy`` (any leading batch shape; last axis 4).

``xyxy`` = (x_min, y_min, x_max, y_max); ``xywh`` = (cx, cy, w, h). :func:`bbox_ciou` follows
YOLOv5 v7.0 ``utils/metrics.py:bbox_iou(..., CIoU=True)`` term by term (eps 1e-7, the
``alpha`` weight computed without gradient).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp


def box_area(b):
    """Area of xyxy boxes (negative extents clip to 0)."""
    return jnp.clip(b[..., 2] - b[..., 0], 0) * jnp.clip(b[..., 3] - b[..., 1], 0)


def box_iou(a, b):
    """Pairwise IoU of xyxy boxes: ``a (..., N, 4)``, ``b (..., M, 4)`` -> ``(..., N, M)``."""
    a = jnp.asarray(a)[..., :, None, :]
    b = jnp.asarray(b)[..., None, :, :]
    lt = jnp.maximum(a[..., :2], b[..., :2])
    rb = jnp.minimum(a[..., 2:], b[..., 2:])
    wh = jnp.clip(rb - lt, 0)
    inter = wh[..., 0] * wh[..., 1]
    union = box_area(a) + box_area(b) - inter
    return inter / jnp.maximum(union, 1e-12)


def _iou_terms(a, b, xywh, eps):
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    if xywh:
        (x1, y1, w1, h1) = (a[..., i] for i in range(4))
        (x2, y2, w2, h2) = (b[..., i] for i in range(4))
        b1_x1, b1_x2, b1_y1, b1_y2 = x1 - w1 / 2, x1 + w1 / 2, y1 - h1 / 2, y1 + h1 / 2
        b2_x1, b2_x2, b2_y1, b2_y2 = x2 - w2 / 2, x2 + w2 / 2, y2 - h2 / 2, y2 + h2 / 2
    else:
        b1_x1, b1_y1, b1_x2, b1_y2 = (a[..., i] for i in range(4))
        b2_x1, b2_y1, b2_x2, b2_y2 = (b[..., i] for i in range(4))
        w1, h1 = b1_x2 - b1_x1, jnp.maximum(b1_y2 - b1_y1, eps)
        w2, h2 = b2_x2 - b2_x1, jnp.maximum(b2_y2 - b2_y1, eps)
    inter = jnp.clip(jnp.minimum(b1_x2, b2_x2) - jnp.maximum(b1_x1, b2_x1), 0) * jnp.clip(
        jnp.minimum(b1_y2, b2_y2) - jnp.maximum(b1_y1, b2_y1), 0
    )
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    return iou, (b1_x1, b1_y1, b1_x2, b1_y2, b2_x1, b2_y1, b2_x2, b2_y2, w1, h1, w2, h2)


def bbox_ciou(a, b, xywh: bool = True, eps: float = 1e-7):
    """Complete IoU (Zheng et al. 2020) of matching boxes, as YOLOv5 computes it:

    ``CIoU = IoU - rho^2 / c^2 - alpha * v`` with ``rho`` the centre distance, ``c`` the
    diagonal of the smallest enclosing box, ``v = 4/pi^2 (atan(w2/h2) - atan(w1/h1))^2`` and
    ``alpha = v / (v - IoU + 1 + eps)`` (no gradient through alpha). ``a`` is the prediction,
    ``b`` the target; ``xywh`` selects the box format.
    """
    iou, (b1_x1, b1_y1, b1_x2, b1_y2, b2_x1, b2_y1, b2_x2, b2_y2, w1, h1, w2, h2) = _iou_terms(
        a, b, xywh, eps
    )
    cw = jnp.maximum(b1_x2, b2_x2) - jnp.minimum(b1_x1, b2_x1)
    ch = jnp.maximum(b1_y2, b2_y2) - jnp.minimum(b1_y1, b2_y1)
    c2 = cw**2 + ch**2 + eps
    rho2 = ((b2_x1 + b2_x2 - b1_x1 - b1_x2) ** 2 + (b2_y1 + b2_y2 - b1_y1 - b1_y2) ** 2) / 4
    v = (4 / math.pi**2) * (jnp.arctan(w2 / h2) - jnp.arctan(w1 / h1)) ** 2
    alpha = jax.lax.stop_gradient(v / (v - iou + (1 + eps)))
    return iou - (rho2 / c2 + v * alpha)
