"""mAP against pycocotools' COCOeval, and the VOC07 11-point variant by hand."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest

from uavcal_jax.detect.metrics import box_iou_np, evaluate_detections, fitness


def _random_set(seed: int, n_img: int = 12, n_cls: int = 4):
    rng = np.random.default_rng(seed)
    gts, dts = [], []
    for i in range(n_img):
        n_gt = 0 if i % 5 == 0 else int(rng.integers(1, 9))  # some images have no gt
        xy = rng.uniform(0, 200, (n_gt, 2))
        wh = rng.uniform(8, 80, (n_gt, 2))
        gb = np.concatenate([xy, xy + wh], 1)
        gc = rng.integers(0, n_cls, n_gt)
        # detections: jittered copies of gt (some) + random false positives
        keep = rng.random(n_gt) < 0.8
        jit = gb[keep] + rng.normal(0, 6, (int(keep.sum()), 4))
        jit[:, 2:] = np.maximum(jit[:, 2:], jit[:, :2] + 2)
        dc = gc[keep].copy()
        flip = rng.random(len(dc)) < 0.1
        dc[flip] = rng.integers(0, n_cls, int(flip.sum()))
        n_fp = int(rng.integers(0, 6))
        fxy = rng.uniform(0, 200, (n_fp, 2))
        fb = np.concatenate([fxy, fxy + rng.uniform(5, 60, (n_fp, 2))], 1)
        db = np.concatenate([jit, fb])
        dcls = np.concatenate([dc, rng.integers(0, n_cls, n_fp)])
        ds = rng.random(len(db))
        gts.append((gb, gc))
        dts.append((db, ds, dcls))
    return gts, dts


def _pycocotools(gts, dts, n_cls, max_dets=100):
    coco_mod = pytest.importorskip("pycocotools.coco")
    cocoeval_mod = pytest.importorskip("pycocotools.cocoeval")
    images, anns, results = [], [], []
    ann_id = 1
    for i, ((gb, gc), (db, ds, dc)) in enumerate(zip(gts, dts, strict=True)):
        images.append({"id": i + 1, "width": 300, "height": 300, "file_name": f"{i}.jpg"})
        for b, c in zip(gb, gc, strict=True):
            w, h = b[2] - b[0], b[3] - b[1]
            anns.append({"id": ann_id, "image_id": i + 1, "category_id": int(c) + 1,
                         "bbox": [float(b[0]), float(b[1]), float(w), float(h)],
                         "area": float(w * h), "iscrowd": 0})
            ann_id += 1
        for b, s, c in zip(db, ds, dc, strict=True):
            results.append({"image_id": i + 1, "category_id": int(c) + 1, "score": float(s),
                            "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]),
                                     float(b[3] - b[1])]})
    gt = coco_mod.COCO()
    gt.dataset = {"images": images, "annotations": anns,
                  "categories": [{"id": k + 1, "name": str(k)} for k in range(n_cls)]}
    with contextlib.redirect_stdout(io.StringIO()):
        gt.createIndex()
        dt = gt.loadRes(results)
        ev = cocoeval_mod.COCOeval(gt, dt, "bbox")
        ev.params.maxDets = sorted({1, 10, 100, max_dets})
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    # precision[T, R, K, area, maxDets] at area "all" and our max_dets
    prec = ev.eval["precision"][:, :, :, 0, ev.params.maxDets.index(max_dets)]

    def mean(p):
        return float(np.mean(p[p > -1])) if np.any(p > -1) else -1.0

    if max_dets == 100:  # also check against the official summary numbers
        assert mean(prec) == pytest.approx(ev.stats[0], abs=1e-12)
    return mean(prec), mean(prec[0]), mean(prec[5])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_map_matches_pycocotools(seed):
    n_cls = 4
    gts, dts = _random_set(seed, n_cls=n_cls)
    ref = _pycocotools(gts, dts, n_cls)
    ours = evaluate_detections([g[0] for g in gts], [g[1] for g in gts], [d[0] for d in dts],
                               [d[1] for d in dts], [d[2] for d in dts], num_classes=n_cls)
    assert ours.map50_95 == pytest.approx(ref[0], abs=1e-4)
    assert ours.map50 == pytest.approx(ref[1], abs=1e-4)
    assert ours.map75 == pytest.approx(ref[2], abs=1e-4)
    assert 0.0 < ours.map50_95 < ours.map50 <= 1.0


def test_map_matches_pycocotools_with_max_dets_and_missing_class():
    # many detections per image (maxDets cut matters) and a class that has no gt at all
    n_cls = 3
    gts, dts = _random_set(7, n_img=6, n_cls=2)
    rng = np.random.default_rng(0)
    dts = [(np.concatenate([db] * 8) + rng.normal(0, 3, (len(db) * 8, 4)),
            rng.random(len(db) * 8), np.concatenate([dc] * 7 + [np.full(len(dc), 2)]))
           for db, ds, dc in dts]
    for db, _, _ in dts:
        db[:, 2:] = np.maximum(db[:, 2:], db[:, :2] + 1)
    ref = _pycocotools(gts, dts, n_cls, max_dets=10)
    ours = evaluate_detections([g[0] for g in gts], [g[1] for g in gts], [d[0] for d in dts],
                               [d[1] for d in dts], [d[2] for d in dts], num_classes=n_cls,
                               max_dets=10)
    assert ours.map50_95 == pytest.approx(ref[0], abs=1e-4)
    assert ours.map50 == pytest.approx(ref[1], abs=1e-4)
    assert np.isnan(ours.ap[2]).all()


def test_perfect_and_empty():
    b = [np.array([[0, 0, 10, 10], [20, 20, 40, 50.0]])]
    c = [np.array([0, 1])]
    r = evaluate_detections(b, c, b, [np.array([0.9, 0.8])], c)
    assert r.map50 == pytest.approx(1.0) and r.map50_95 == pytest.approx(1.0)
    r = evaluate_detections(b, c, [np.zeros((0, 4))], [np.zeros(0)], [np.zeros(0, int)])
    assert r.map50 == 0.0
    assert fitness(r.as_dict(), "fitness") == 0.0


def test_ignored_ground_truth_is_neither_tp_nor_fp():
    gt = [np.array([[0, 0, 10, 10], [50, 50, 60, 60.0]])]
    cls = [np.array([0, 0])]
    det = [np.array([[0, 0, 10, 10], [50, 50, 60, 60.0]])]
    r = evaluate_detections(gt, cls, det, [np.array([0.5, 0.9])], cls,
                            gt_ignore=[np.array([False, True])])
    assert r.num_gt[0] == 1
    assert r.map50 == pytest.approx(1.0)


def test_voc07_eleven_point():
    # one class, 2 gts; detections: TP (0.9), FP (0.8), TP (0.7) -> rc [.5,.5,1], pr [1,.5,.667]
    gt = [np.array([[0, 0, 10, 10], [20, 0, 30, 10.0]])]
    cls = [np.array([0, 0])]
    det = [np.array([[0, 0, 10, 10], [100, 100, 110, 110], [20, 0, 30, 10.0]])]
    r = evaluate_detections(gt, cls, det, [np.array([0.9, 0.8, 0.7])], [np.zeros(3, int)],
                            interpolation="voc07", iou_thresholds=[0.5])
    expected = (6 * 1.0 + 5 * (2 / 3)) / 11
    assert r.map50 == pytest.approx(expected)


def test_box_iou_np():
    a = np.array([[0, 0, 10, 10.0]])
    b = np.array([[5, 0, 15, 10.0], [20, 20, 30, 30]])
    np.testing.assert_allclose(box_iou_np(a, b), [[50 / 150, 0.0]])
