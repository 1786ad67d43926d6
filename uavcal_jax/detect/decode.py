"""YOLOv5 ``Detect`` inference decoding: raw outputs -> boxes in input pixels.

For cell (gx, gy), anchor (aw, ah) and stride s: ``xy = (2 sigmoid(t_xy) - 0.5 + g) * s``,
``wh = (2 sigmoid(t_wh))^2 * anchor``; objectness and class probabilities are sigmoids. The
``N = sum_l H_l W_l na`` predictions are ordered level, row, column, anchor.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.detect.config import DetectorConfig


def decode_level(p, stride: float, anchors_px):
    """One level ``(B, ny, nx, na, 5+C)`` -> xywh ``(B, ny, nx, na, 4)`` px, obj, cls_prob."""
    p = p.astype(jnp.float32)
    _, ny, nx, _, _ = p.shape
    gy, gx = jnp.meshgrid(jnp.arange(ny, dtype=jnp.float32), jnp.arange(nx, dtype=jnp.float32),
                          indexing="ij")
    grid = jnp.stack([gx, gy], axis=-1)[None, :, :, None, :]  # (1,ny,nx,1,2)
    s = jax.nn.sigmoid(p)
    xy = (s[..., 0:2] * 2.0 - 0.5 + grid) * stride
    wh = (s[..., 2:4] * 2.0) ** 2 * jnp.asarray(anchors_px, jnp.float32)[None, None, None]
    return jnp.concatenate([xy, wh], axis=-1), s[..., 4], s[..., 5:]


def decode(outputs, config: DetectorConfig):
    """-> ``boxes (B, N, 4)`` xyxy px, ``obj (B, N)``, ``cls_prob (B, N, C)``."""
    boxes, objs, clss = [], [], []
    for i, p in enumerate(outputs):
        xywh, obj, cls = decode_level(p, float(config.strides[i]), config.anchors[i])
        b = p.shape[0]
        xy, wh = xywh[..., :2], xywh[..., 2:]
        boxes.append(jnp.concatenate([xy - wh / 2, xy + wh / 2], -1).reshape(b, -1, 4))
        objs.append(obj.reshape(b, -1))
        clss.append(cls.reshape(b, -1, cls.shape[-1]))
    return jnp.concatenate(boxes, 1), jnp.concatenate(objs, 1), jnp.concatenate(clss, 1)
