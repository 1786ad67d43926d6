"""Non-maximum suppression that runs under ``jit`` with fixed-size outputs.

:func:`nms` is greedy NMS (torchvision semantics: walk the boxes by descending score, keep a
box unless a kept box overlaps it with IoU > ``iou_thresh``), made class-aware with YOLOv5's
class-offset trick (each box is shifted by ``class * max_wh`` so boxes of different classes
never overlap). It is a ``lax.while_loop`` that takes the best remaining candidate and
suppresses its overlaps, one kept box per iteration, so it costs ``O(kept x K)`` and stops as
soon as no candidate is left or ``max_det`` are kept. Before it, the candidates are cut to the
``pre_nms_topk`` highest scores (YOLOv5 uses ``max_nms = 30000``; 1,000 is plenty for real
images and makes the step cheap).

:func:`postprocess` follows v7.0 ``utils/general.py:non_max_suppression``: a candidate needs
``obj > conf_thresh``; its score is ``obj * cls_prob``; with ``multi_label`` every
(box, class) pair with score > ``conf_thresh`` is a candidate (as ``val.py`` does), otherwise
each box takes its best class (as ``detect.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.detect.config import SERVE_PREDICT, DetectorConfig, PredictConfig

MAX_WH = 7680.0  # YOLOv5's class offset (maximum box width/height in pixels)


class Detections(NamedTuple):
    """Fixed-size detections (a pytree): padded rows have ``valid = False`` and zeros."""

    boxes: jax.Array  # (..., max_det, 4) xyxy pixels of the network input
    scores: jax.Array  # (..., max_det)
    classes: jax.Array  # (..., max_det) int32
    valid: jax.Array  # (..., max_det) bool


def _iou_one_to_many(box, boxes):
    lt = jnp.maximum(box[:2], boxes[:, :2])
    rb = jnp.minimum(box[2:], boxes[:, 2:])
    wh = jnp.clip(rb - lt, 0.0)
    inter = wh[:, 0] * wh[:, 1]
    area = lambda b: (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])  # noqa: E731
    union = area(box) + area(boxes) - inter
    return inter / jnp.maximum(union, 1e-12)


def greedy_nms_indices(boxes, scores, valid, *, max_det: int, iou_thresh: float,
                       presorted: bool = False):
    """Greedy NMS of one image. ``boxes (K,4)`` (already class-offset), ``scores (K,)``,
    ``valid (K,)``. Returns ``(idx (max_det,) int32, keep (max_det,) bool)``, best first.
    ``presorted``: the valid candidates already come in descending score order (top-k)."""
    if presorted:
        order = jnp.arange(boxes.shape[0])
        sb, avail0 = boxes, valid
    else:
        neg = jnp.finfo(jnp.float32).min
        s = jnp.where(valid, scores, neg)
        # stable descending order (ties keep the lower index first, like a stable sort)
        order = jnp.argsort(-s, stable=True)
        sb = boxes[order]
        avail0 = valid[order]

    def cond(state):
        n, avail, _ = state
        return (n < max_det) & jnp.any(avail)

    def body(state):
        n, avail, out = state
        i = jnp.argmax(avail)  # first (= highest-scoring) remaining candidate
        iou = _iou_one_to_many(sb[i], sb)
        avail = avail & ~(iou > iou_thresh)
        avail = avail.at[i].set(False)
        out = out.at[n].set(order[i].astype(jnp.int32))
        return n + 1, avail, out

    n, _, out = jax.lax.while_loop(
        cond, body, (jnp.int32(0), avail0, jnp.zeros((max_det,), jnp.int32))
    )
    keep = jnp.arange(max_det) < n
    return out, keep


def _nms_single(boxes, scores, classes, valid, max_det, iou_thresh, max_wh, pre_nms_topk,
                agnostic, presorted=False):
    n = boxes.shape[0]
    classes = classes.astype(jnp.int32)
    if valid is None:
        valid = jnp.ones((n,), bool)
    if pre_nms_topk is not None and n > pre_nms_topk:
        neg = jnp.finfo(jnp.float32).min
        _, top = jax.lax.top_k(jnp.where(valid, scores, neg), pre_nms_topk)
        boxes, scores, classes, valid = boxes[top], scores[top], classes[top], valid[top]
        presorted = True
    off = boxes if agnostic else boxes + (classes.astype(boxes.dtype) * max_wh)[:, None]
    idx, keep = greedy_nms_indices(
        off, scores, valid, max_det=max_det, iou_thresh=iou_thresh, presorted=presorted
    )
    return Detections(
        boxes=jnp.where(keep[:, None], boxes[idx], 0.0),
        scores=jnp.where(keep, scores[idx], 0.0),
        classes=jnp.where(keep, classes[idx], 0),
        valid=keep,
    )


def nms(
    boxes,
    scores,
    classes,
    *,
    max_det: int = SERVE_PREDICT.max_det,
    iou_thresh: float = SERVE_PREDICT.iou_thresh,
    valid=None,
    max_wh: float = MAX_WH,
    pre_nms_topk: int | None = None,
    agnostic: bool = False,
    presorted: bool = False,
) -> Detections:
    """Class-aware greedy NMS with a fixed number of outputs.

    ``boxes (N, 4)`` xyxy, ``scores (N,)``, ``classes (N,)`` (and optional ``valid (N,)``);
    a leading batch axis is vmapped. Returns :class:`Detections` with ``max_det`` rows sorted
    by descending score. ``pre_nms_topk`` keeps only that many top-scoring candidates first;
    ``agnostic`` suppresses across classes (the class offset is left out); ``presorted``
    promises that valid candidates are already in descending score order (skips a sort).
    """
    boxes = jnp.asarray(boxes, jnp.float32)
    scores = jnp.asarray(scores, jnp.float32)
    classes = jnp.asarray(classes)
    if valid is not None:
        valid = jnp.asarray(valid, bool)

    def single(b, s, c, v):
        return _nms_single(b, s, c, v, max_det, iou_thresh, max_wh, pre_nms_topk, agnostic,
                           presorted)

    if boxes.ndim == 3:
        if valid is None:
            valid = jnp.ones(scores.shape, bool)
        return jax.vmap(single)(boxes, scores, classes, valid)
    return single(boxes, scores, classes, valid)


def _grid_constants(config: DetectorConfig, shapes):
    """Per-prediction cell xy, anchor wh and stride (NumPy constants), ordered as decode()."""
    gxy, awh, st = [], [], []
    for i, (ny, nx, na) in enumerate(shapes):
        gy, gx, a = np.meshgrid(np.arange(ny), np.arange(nx), np.arange(na), indexing="ij")
        gxy.append(np.stack([gx, gy], -1).reshape(-1, 2))
        awh.append(np.asarray(config.anchors[i], np.float32)[a.reshape(-1)])
        st.append(np.full(ny * nx * na, config.strides[i], np.float32))
    return (np.concatenate(gxy).astype(np.float32), np.concatenate(awh).astype(np.float32),
            np.concatenate(st))


def postprocess(
    outputs,
    config: DetectorConfig,
    predict_cfg: PredictConfig = SERVE_PREDICT,
) -> Detections:
    """Raw head outputs -> :class:`Detections` ``(B, max_det, ...)`` in input pixels.

    Scores are computed for every prediction, but boxes are decoded (as :func:`decode`) only
    for the ``predict_cfg.pre_nms_topk`` best candidates, which then go through :func:`nms`.
    """
    conf_thresh, pre_nms_topk = predict_cfg.conf_thresh, predict_cfg.pre_nms_topk
    b = outputs[0].shape[0]
    no = outputs[0].shape[-1]
    c = no - 5
    raw = jnp.concatenate([o.reshape(b, -1, no).astype(jnp.float32) for o in outputs], 1)
    n = raw.shape[1]
    gxy, awh, st = _grid_constants(config, [o.shape[1:4] for o in outputs])
    obj = jax.nn.sigmoid(raw[..., 4])
    conf = obj[..., None] * jax.nn.sigmoid(raw[..., 5:])  # (B,N,C)
    neg = -1.0
    if predict_cfg.multi_label and c > 1:
        flat = conf.reshape(b, n * c)
        ok = (jnp.repeat(obj, c, axis=1) > conf_thresh) & (flat > conf_thresh)
        k = min(pre_nms_topk, n * c)
        _, top = jax.lax.top_k(jnp.where(ok, flat, neg), k)
        scores = jnp.take_along_axis(flat, top, 1)
        valid = jnp.take_along_axis(ok, top, 1)
        rows = top // c
        classes = (top % c).astype(jnp.int32)
    else:
        best = jnp.max(conf, axis=-1)
        cls = jnp.argmax(conf, axis=-1).astype(jnp.int32)
        ok = (obj > conf_thresh) & (best > conf_thresh)
        k = min(pre_nms_topk, n)
        _, rows = jax.lax.top_k(jnp.where(ok, best, neg), k)
        scores = jnp.take_along_axis(best, rows, 1)
        valid = jnp.take_along_axis(ok, rows, 1)
        classes = jnp.take_along_axis(cls, rows, 1)
    # decode the selected rows: xy = (2 sig - 0.5 + cell) * stride, wh = (2 sig)^2 * anchor
    sig = jax.nn.sigmoid(jnp.take_along_axis(raw[..., :4], rows[..., None], 1))
    stride = jnp.asarray(st)[rows][..., None]
    xy = (sig[..., :2] * 2.0 - 0.5 + jnp.asarray(gxy)[rows]) * stride
    wh = (sig[..., 2:4] * 2.0) ** 2 * jnp.asarray(awh)[rows]
    boxes = jnp.concatenate([xy - wh / 2, xy + wh / 2], -1)
    return nms(
        boxes,
        scores,
        classes,
        max_det=predict_cfg.max_det,
        iou_thresh=predict_cfg.iou_thresh,
        valid=valid,
        agnostic=predict_cfg.agnostic,
        presorted=True,
    )
