"""Box conversions, IoU and CIoU against independent NumPy/math references."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.detect.boxes import bbox_ciou, box_iou


def xywh_to_xyxy(b):
    """Centre-size boxes (..., 4) as corners (..., 4)."""
    xy, wh = b[..., :2], b[..., 2:4]
    return jnp.concatenate([xy - wh / 2, xy + wh / 2], axis=-1)


def iou_xywh(a, b, eps=1e-7):
    """Element-wise IoU of matching centre-size boxes (YOLOv5's ``eps`` in the union)."""
    a1, b1 = xywh_to_xyxy(a), xywh_to_xyxy(b)
    wh = jnp.clip(jnp.minimum(a1[..., 2:], b1[..., 2:]) - jnp.maximum(a1[..., :2], b1[..., :2]),
                  0)
    inter = wh[..., 0] * wh[..., 1]
    return inter / (a[..., 2] * a[..., 3] + b[..., 2] * b[..., 3] - inter + eps)


def _ciou_reference(b1, b2):
    """CIoU of two xyxy boxes straight from Zheng et al. (AAAI 2020), eqs. 9-11, in float64."""
    x1, y1, x2, y2 = b1
    u1, v1, u2, v2 = b2
    iw = max(0.0, min(x2, u2) - max(x1, u1))
    ih = max(0.0, min(y2, v2) - max(y1, v1))
    inter = iw * ih
    w1, h1, w2, h2 = x2 - x1, y2 - y1, u2 - u1, v2 - v1
    iou = inter / (w1 * h1 + w2 * h2 - inter)
    c2 = (max(x2, u2) - min(x1, u1)) ** 2 + (max(y2, v2) - min(y1, v1)) ** 2
    rho2 = ((x1 + x2) / 2 - (u1 + u2) / 2) ** 2 + ((y1 + y2) / 2 - (v1 + v2) / 2) ** 2
    v = 4 / math.pi**2 * (math.atan(w2 / h2) - math.atan(w1 / h1)) ** 2
    alpha = v / ((1 - iou) + v) if v > 0 else 0.0
    return iou - rho2 / c2 - alpha * v


def test_box_iou_matches_numpy():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 50, (7, 2))
    a = np.concatenate([a, a + rng.uniform(1, 30, (7, 2))], 1)
    b = rng.uniform(0, 50, (9, 2))
    b = np.concatenate([b, b + rng.uniform(1, 30, (9, 2))], 1)
    ref = np.zeros((7, 9))
    for i in range(7):
        for j in range(9):
            iw = max(0, min(a[i, 2], b[j, 2]) - max(a[i, 0], b[j, 0]))
            ih = max(0, min(a[i, 3], b[j, 3]) - max(a[i, 1], b[j, 1]))
            inter = iw * ih
            ar = lambda x: (x[2] - x[0]) * (x[3] - x[1])  # noqa: E731
            ref[i, j] = inter / (ar(a[i]) + ar(b[j]) - inter)
    np.testing.assert_allclose(np.asarray(box_iou(a, b)), ref, atol=1e-6)


def test_ciou_hand_values():
    # overlapping squares (0,0,2,2) and (1,1,3,3): IoU 1/7, rho^2/c^2 = 2/18, v = 0
    got = float(bbox_ciou(jnp.array([0, 0, 2, 2.0]), jnp.array([1, 1, 3, 3.0]), xywh=False))
    assert got == pytest.approx(1 / 7 - 1 / 9, abs=1e-6)
    # concentric 2x2 and 4x2 boxes: IoU 1/2, rho = 0, v = 4/pi^2 (atan 2 - atan 1)^2
    v = 4 / math.pi**2 * (math.atan(2.0) - math.atan(1.0)) ** 2
    alpha = v / (v + 0.5)
    got = float(bbox_ciou(jnp.array([0, 0, 2, 2.0]), jnp.array([0, 0, 4, 2.0])))
    assert got == pytest.approx(0.5 - alpha * v, abs=1e-6)
    # identical boxes
    assert float(bbox_ciou(jnp.array([5, 5, 3, 4.0]), jnp.array([5, 5, 3, 4.0]))) == pytest.approx(
        1.0, abs=1e-6
    )
    # disjoint boxes: IoU 0, CIoU < 0
    assert float(bbox_ciou(jnp.array([0, 0, 1, 1.0]), jnp.array([10, 10, 1, 1.0]))) < 0


def test_ciou_matches_reference_on_random_boxes():
    rng = np.random.default_rng(2)
    n = 200
    a = np.concatenate([rng.uniform(0, 40, (n, 2)), rng.uniform(1, 30, (n, 2))], 1)
    b = np.concatenate([a[:, :2] + rng.normal(0, 8, (n, 2)), rng.uniform(1, 30, (n, 2))], 1)
    got = np.asarray(bbox_ciou(a.astype(np.float32), b.astype(np.float32)))
    ax, bx = np.asarray(xywh_to_xyxy(jnp.asarray(a))), np.asarray(xywh_to_xyxy(jnp.asarray(b)))
    ref = np.array([_ciou_reference(ax[i], bx[i]) for i in range(n)])
    np.testing.assert_allclose(got, ref, atol=2e-5)
    iou = np.asarray(iou_xywh(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)))
    assert np.all(got <= iou + 1e-6)


def test_ciou_alpha_has_no_gradient_and_grads_finite():
    a = jnp.array([1.0, 2.0, 3.0, 1.5])
    b = jnp.array([1.5, 2.5, 2.0, 3.0])
    g = jax.grad(lambda p: bbox_ciou(p, b))(a)
    assert np.all(np.isfinite(np.asarray(g)))

    # analytic check of the stop-gradient: d/dp with alpha treated as a constant
    def ciou_const_alpha(p, alpha):
        iou = iou_xywh(p, b)
        p1, p2 = xywh_to_xyxy(p), xywh_to_xyxy(b)
        c2 = (jnp.maximum(p1[2], p2[2]) - jnp.minimum(p1[0], p2[0])) ** 2 + (
            jnp.maximum(p1[3], p2[3]) - jnp.minimum(p1[1], p2[1])
        ) ** 2 + 1e-7
        rho2 = jnp.sum((p[:2] - b[:2]) ** 2)
        v = 4 / math.pi**2 * (jnp.arctan(b[2] / b[3]) - jnp.arctan(p[2] / p[3])) ** 2
        return iou - rho2 / c2 - alpha * v

    iou0 = float(iou_xywh(a, b))
    v0 = 4 / math.pi**2 * (math.atan(2.0 / 3.0) - math.atan(3.0 / 1.5)) ** 2
    alpha0 = v0 / (v0 - iou0 + 1 + 1e-7)
    g_ref = jax.grad(ciou_const_alpha)(a, alpha0)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-4, atol=1e-6)


def test_anchor_metrics_and_kmeans():
    from uavcal_jax.detect.anchors import anchor_metrics, check_anchors, kmeans_anchors
    from uavcal_jax.detect.config import YOLOV5_ANCHORS, DetectorConfig

    # hand case: one anchor 10x10; labels 10x10 (r = 1), 30x10 (r = 1/3 > 1/4), 50x10 (1/5)
    bpr, aat = anchor_metrics([[10, 10]], [[10, 10], [30, 10], [50, 10]])
    assert bpr == pytest.approx(2 / 3) and aat == pytest.approx(2 / 3)
    # tiny aerial-like objects: YOLOv5's defaults recall them poorly, k-means fixes that
    rng = np.random.default_rng(0)
    wh = np.concatenate([rng.normal([3, 2], 0.3, (300, 2)), rng.normal([24, 12], 3, (300, 2)),
                         rng.normal([60, 80], 8, (100, 2))]).clip(1.5)
    cfg = DetectorConfig()
    bpr0, _ = anchor_metrics(YOLOV5_ANCHORS, wh)
    assert bpr0 < 0.98
    k = kmeans_anchors(wh, 9, gen=200)
    assert k.shape == (9, 2) and np.all(np.diff(k.prod(1)) >= 0)
    assert anchor_metrics(k, wh)[0] > 0.99
    new_cfg, report = check_anchors(cfg, wh, gen=200)
    assert report["replaced"] and report["bpr_new"] > bpr0
    assert len(new_cfg.anchors) == 3 and all(len(a) == 3 for a in new_cfg.anchors)
    same_cfg, report = check_anchors(cfg, rng.normal([40, 40], 5, (50, 2)))
    assert same_cfg is cfg and not report["replaced"]


def test_label_sizes_are_letterboxed():
    from types import SimpleNamespace

    from uavcal_jax.detect.anchors import label_sizes

    rec = SimpleNamespace(boxes=np.array([[10.0, 20.0, 30.0, 30.0]]), width=200, height=100)
    empty = SimpleNamespace(boxes=np.zeros((0, 4)), width=50, height=50)
    wh = label_sizes(SimpleNamespace(records=[rec, empty]), (64, 96))
    # scale min(96 / 200, 64 / 100) = 0.48 for a 20 x 10 box
    np.testing.assert_allclose(wh, [[9.6, 4.8]])
    assert label_sizes(SimpleNamespace(records=[empty]), (64, 96)).shape == (0, 2)
