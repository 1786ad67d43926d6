"""Jitted fixed-size NMS against OpenCV's batched NMS; postprocess/decode behaviour."""

from __future__ import annotations

import cv2
import jax
import numpy as np
import pytest

from uavcal_jax.detect.config import DetectorConfig, PredictConfig
from uavcal_jax.detect.decode import decode
from uavcal_jax.detect.nms import nms, postprocess


def opencv_nms(boxes, scores, classes, iou_thresh, max_det, valid=None):
    """``cv2.dnn.NMSBoxesBatched`` (per-class greedy NMS, suppress IoU > thresh, IoU without
    the +1 on widths): the indices kept, best first, the first ``max_det`` of them (greedy
    NMS keeps the same prefix whether or not it stops at ``max_det``)."""
    idx = np.arange(len(scores)) if valid is None else np.flatnonzero(valid)
    if not len(idx):
        return np.zeros(0, int)
    b = boxes[idx].astype(np.float64)
    xywh = np.concatenate([b[:, :2], b[:, 2:] - b[:, :2]], 1)  # OpenCV's Rect2d
    kept = cv2.dnn.NMSBoxesBatched(xywh, scores[idx].astype(np.float32),
                                   classes[idx].astype(np.int32), -1.0, float(iou_thresh))
    return idx[np.asarray(kept, int).reshape(-1)][:max_det]


def _assert_no_near_threshold_pairs(boxes, classes, iou_thresh, valid=None, gap=1e-5):
    """Float32 (ours) and float64 (OpenCV) IoUs differ by ~1e-7 on these boxes, so they can
    disagree only on a pair within that of the threshold: make sure no same-class pair is."""
    idx = np.arange(len(boxes)) if valid is None else np.flatnonzero(valid)
    b = boxes[idx].astype(np.float64)
    lt = np.maximum(b[:, None, :2], b[None, :, :2])
    rb = np.minimum(b[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), -1)
    area = np.prod(b[:, 2:] - b[:, :2], -1)
    iou = inter / (area[:, None] + area[None] - inter)
    same = classes[idx][:, None] == classes[idx][None]
    assert not np.any(same & (np.abs(iou - iou_thresh) < gap))


def _random_boxes(rng, n, n_cls, size=200.0):
    """Random boxes, distinct scores (no ties: the order is then the same everywhere)."""
    xy = rng.uniform(0, size, (n, 2))
    wh = rng.uniform(5, 60, (n, 2))
    boxes = np.concatenate([xy, xy + wh], 1).astype(np.float32)
    scores = ((rng.permutation(n) + 1) / (n + 1)).astype(np.float32)
    classes = rng.integers(0, n_cls, n).astype(np.int32)
    return boxes, scores, classes


@pytest.mark.parametrize("seed,n,n_cls,thr", [(0, 300, 1, 0.45), (1, 500, 4, 0.5), (2, 80, 3, 0.3)])
def test_matches_opencv_batched_nms(seed, n, n_cls, thr):
    rng = np.random.default_rng(seed)
    boxes, scores, classes = _random_boxes(rng, n, n_cls)
    _assert_no_near_threshold_pairs(boxes, classes, thr)
    f = jax.jit(lambda b, s, c: nms(b, s, c, max_det=300, iou_thresh=thr))
    det = f(boxes, scores, classes)
    ref = opencv_nms(boxes, scores, classes, thr, 300)
    nv = int(det.valid.sum())
    assert nv == len(ref)
    np.testing.assert_allclose(np.asarray(det.boxes[:nv]), boxes[ref])
    np.testing.assert_allclose(np.asarray(det.scores[:nv]), scores[ref])
    np.testing.assert_array_equal(np.asarray(det.classes[:nv]), classes[ref])
    assert not np.asarray(det.valid[nv:]).any()
    assert np.all(np.asarray(det.scores[nv:]) == 0)


def test_valid_mask_max_det_and_batch():
    rng = np.random.default_rng(3)
    b = np.stack([_random_boxes(rng, 200, 2)[0] for _ in range(3)])
    s = np.stack([_random_boxes(rng, 200, 2)[1] for _ in range(3)])
    c = rng.integers(0, 2, (3, 200)).astype(np.int32)
    v = rng.random((3, 200)) < 0.7
    det = jax.jit(lambda *a: nms(*a[:3], valid=a[3], max_det=10, iou_thresh=0.45))(b, s, c, v)
    assert det.boxes.shape == (3, 10, 4) and det.valid.shape == (3, 10)
    for i in range(3):
        _assert_no_near_threshold_pairs(b[i], c[i], 0.45, v[i])
        ref = opencv_nms(b[i], s[i], c[i], 0.45, 10, valid=v[i])
        nv = int(det.valid[i].sum())
        assert nv == len(ref) == 10
        np.testing.assert_allclose(np.asarray(det.scores[i, :nv]), s[i][ref])


def test_pre_topk_and_no_candidates():
    rng = np.random.default_rng(4)
    boxes, scores, classes = _random_boxes(rng, 400, 2)
    # with the candidates cut to the best 1000 > n, nothing changes
    a = nms(boxes, scores, classes, max_det=50, pre_nms_topk=1000)
    b = nms(boxes, scores, classes, max_det=50)
    np.testing.assert_array_equal(np.asarray(a.scores), np.asarray(b.scores))
    # top-k 100: same as NumPy NMS over the 100 best boxes
    c = nms(boxes, scores, classes, max_det=300, pre_nms_topk=100)
    top = np.argsort(-scores, kind="stable")[:100]
    ref = opencv_nms(boxes[top], scores[top], classes[top], 0.45, 300)
    np.testing.assert_allclose(np.asarray(c.scores[: len(ref)]), scores[top][ref])
    assert int(c.valid.sum()) == len(ref)
    none = nms(boxes, scores, classes, valid=np.zeros(400, bool), max_det=20)
    assert not np.asarray(none.valid).any()


def test_class_offset_keeps_overlapping_boxes_of_other_classes():
    boxes = np.array([[10, 10, 50, 50], [12, 12, 52, 52], [11, 11, 51, 51]], np.float32)
    scores = np.array([0.9, 0.8, 0.7], np.float32)
    det = nms(boxes, scores, np.array([0, 1, 0]), max_det=5, iou_thresh=0.5)
    np.testing.assert_allclose(np.asarray(det.scores[:2]), [0.9, 0.8])
    assert int(det.valid.sum()) == 2
    det = nms(boxes, scores, np.array([0, 1, 0]), max_det=5, iou_thresh=0.5, agnostic=True)
    assert int(det.valid.sum()) == 1


def _outputs_with_one_object(cfg):
    outs = [np.full((1, h, w, 3, cfg.num_outputs), -10.0, np.float32) for h, w in cfg.grid_sizes()]
    # level 0, cell (gx=5, gy=3), anchor 1: sigmoid(0) = 0.5 -> xy = (0.5*2-0.5+g)*8,
    # wh = (2*0.5)^2 * anchor
    outs[0][0, 3, 5, 1, :4] = 0.0
    outs[0][0, 3, 5, 1, 4] = 4.0  # objectness
    outs[0][0, 3, 5, 1, 5 + 1] = 3.0  # class 1
    return tuple(outs)


def test_decode_and_postprocess_single_object():
    cfg = DetectorConfig(num_classes=3, img_size=(64, 96))
    outs = _outputs_with_one_object(cfg)
    boxes, obj, cls = decode(outs, cfg)
    n = sum(h * w * 3 for h, w in cfg.grid_sizes())
    assert boxes.shape == (1, n, 4) and obj.shape == (1, n) and cls.shape == (1, n, 3)
    i = (3 * 12 + 5) * 3 + 1  # level 0 ordering: row, column, anchor
    cx, cy = (0.5 + 5) * 8, (0.5 + 3) * 8
    aw, ah = cfg.anchors[0][1]
    np.testing.assert_allclose(
        np.asarray(boxes[0, i]), [cx - aw / 2, cy - ah / 2, cx + aw / 2, cy + ah / 2], atol=1e-4
    )
    det = jax.jit(lambda o: postprocess(o, cfg, PredictConfig(conf_thresh=0.25, max_det=7)))(outs)
    assert det.boxes.shape == (1, 7, 4)
    assert int(det.valid.sum()) == 1
    assert int(det.classes[0, 0]) == 1
    expect = 1 / (1 + np.exp(-4.0)) / (1 + np.exp(-3.0))
    assert float(det.scores[0, 0]) == pytest.approx(expect, rel=1e-5)
    outs[0][0, 3, 5, 1, 5 + 0] = 0.0  # class 0 probability 0.5: a second label
    ml = postprocess(outs, cfg, PredictConfig(conf_thresh=0.01, max_det=7, multi_label=True))
    # multi-label: the same box appears once per class above the threshold (class 2 is not)
    assert int(ml.valid.sum()) == 2
    np.testing.assert_array_equal(np.asarray(ml.classes[0, :2]), [1, 0])
    np.testing.assert_allclose(np.asarray(ml.boxes[0, 0]), np.asarray(ml.boxes[0, 1]))
    single = postprocess(outs, cfg, PredictConfig(conf_thresh=0.01, max_det=7))
    assert int(single.valid.sum()) == 1


@pytest.mark.parametrize("multi_label", [False, True])
def test_postprocess_equals_nms_of_decoded_boxes(multi_label):
    cfg = DetectorConfig(num_classes=3, img_size=(64, 96))
    rng = np.random.default_rng(9)
    outs = tuple(rng.normal(0, 2, (2, h, w, 3, 8)).astype(np.float32) for h, w in cfg.grid_sizes())
    det = postprocess(outs, cfg, PredictConfig(conf_thresh=0.05, max_det=40,
                                            multi_label=multi_label))
    boxes, obj, cls = (np.asarray(a) for a in decode(outs, cfg))
    conf = obj[..., None] * cls
    for b in range(2):
        if multi_label:
            bb = np.repeat(boxes[b], 3, 0)
            ss = conf[b].reshape(-1)
            cc = np.tile(np.arange(3), len(boxes[b]))
            vv = (np.repeat(obj[b], 3) > 0.05) & (ss > 0.05)
        else:
            bb, ss, cc = boxes[b], conf[b].max(-1), conf[b].argmax(-1)
            vv = (obj[b] > 0.05) & (ss > 0.05)
        ref = opencv_nms(bb, ss, cc, 0.45, 40, valid=vv)
        nv = int(det.valid[b].sum())
        assert nv == len(ref)
        np.testing.assert_allclose(np.asarray(det.scores[b, :nv]), ss[ref], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(det.boxes[b, :nv]), bb[ref], atol=1e-3)
        np.testing.assert_array_equal(np.asarray(det.classes[b, :nv]), cc[ref])
