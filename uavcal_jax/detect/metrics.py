"""Detection mAP: COCO's mAP@0.5 and mAP@[.5:.95] (101-point interpolation), VOC07 11-point.

A NumPy re-implementation of ``pycocotools.cocoeval.COCOeval`` for boxes with area range
"all" and one ``maxDets`` (100 by default), which the tests check against pycocotools to
1e-4. Semantics replicated exactly:

- per image and class, detections are sorted by score (stable) and cut to ``max_dets``;
  ground truth is ordered non-ignored first;
- for each IoU threshold, each detection in score order takes the still-unmatched ground
  truth with the highest IoU ``>= threshold`` (the last of equal ones); a detection whose
  best ground truth is an "ignore" one (VOC ``difficult``, COCO ``iscrowd``) is ignored, and
  an ignore ground truth is only taken when no regular one qualifies;
- per class, detections of all images are sorted by score (stable, images in order), the
  precision curve is made monotone and read at the recall thresholds (101 points
  ``0:.01:1`` for COCO, 11 points ``0:.1:1`` for VOC07); classes without (non-ignored)
  ground truth are left out of the mean.

IoU is computed as pycocotools does (no +1 on widths). Crowd ground truth (IoU over the
detection's area, several matches) is not modelled: ``iscrowd`` annotations are plain
"ignore" boxes here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: pycocotools' thresholds, built the same way so that float comparisons agree bit for bit.
#: pycocotools' default ``maxDets``: detections counted per image (and class).
COCO_MAX_DETS = 100
COCO_IOU_THRESHOLDS = np.linspace(.5, 0.95, int(np.round((0.95 - .5) / .05)) + 1, endpoint=True)
COCO_RECALL_THRESHOLDS = np.linspace(.0, 1.00, int(np.round((1.00 - .0) / .01)) + 1,
                                     endpoint=True)
VOC07_RECALL_THRESHOLDS = np.linspace(0.0, 1.0, 11)


@dataclass(frozen=True)
class MapResult:
    """mAP and its pieces.

    Attributes:
        map50: mean AP at IoU 0.5 over classes with ground truth.
        map50_95: mean AP over IoU 0.5:0.05:0.95 and classes with ground truth.
        map75: mean AP at IoU 0.75.
        ap: (C, T) AP per class and IoU threshold (NaN for classes without ground truth).
        precision: (T, R, C) interpolated precision at the recall thresholds (-1: no gt).
        recall: (T, C) final recall (-1: no gt).
        iou_thresholds: (T,); num_gt: (C,) non-ignored ground-truth boxes per class.
    """

    map50: float
    map50_95: float
    map75: float
    ap: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    iou_thresholds: np.ndarray
    num_gt: np.ndarray

    def as_dict(self, class_names=None) -> dict:
        out = {"map50": self.map50, "map50_95": self.map50_95, "map75": self.map75}
        t50 = int(np.argmin(np.abs(self.iou_thresholds - 0.5)))
        names = class_names or [str(i) for i in range(self.ap.shape[0])]
        out["per_class"] = {
            str(n): {"ap50": None if np.isnan(self.ap[i, t50]) else float(self.ap[i, t50]),
                     "ap50_95": None if np.all(np.isnan(self.ap[i])) else
                     float(np.nanmean(self.ap[i])),
                     "num_gt": int(self.num_gt[i])}
            for i, n in enumerate(names)}
        return out


def box_iou_np(dt: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(D, G) IoU of xyxy boxes, computed as pycocotools' ``bbIou`` (float64)."""
    dt = np.asarray(dt, dtype=np.float64).reshape(-1, 4)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 4)
    # go through x, y, w, h as pycocotools does
    dx, dy, dw, dh = dt[:, 0], dt[:, 1], dt[:, 2] - dt[:, 0], dt[:, 3] - dt[:, 1]
    gx, gy, gw, gh = gt[:, 0], gt[:, 1], gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]
    w = (np.minimum((dw + dx)[:, None], (gw + gx)[None]) - np.maximum(dx[:, None], gx[None]))
    h = (np.minimum((dh + dy)[:, None], (gh + gy)[None]) - np.maximum(dy[:, None], gy[None]))
    inter = np.where((w > 0) & (h > 0), w * h, 0.0)
    union = (dw * dh)[:, None] + (gw * gh)[None] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / union, 0.0)


def _match(ious: np.ndarray, gt_ignore: np.ndarray, thresholds: np.ndarray):
    """Greedy matching of score-sorted detections for all thresholds at once.

    Returns ``dt_matched (T, D) bool`` and ``dt_ignored (T, D) bool``.
    """
    n_t = len(thresholds)
    n_d, n_g = ious.shape
    dt_matched = np.zeros((n_t, n_d), bool)
    dt_ignored = np.zeros((n_t, n_d), bool)
    if n_g == 0 or n_d == 0:
        return dt_matched, dt_ignored
    gt_taken = np.zeros((n_t, n_g), bool)
    thr = np.minimum(thresholds, 1 - 1e-10)[:, None]
    rows = np.arange(n_t)
    rev = np.arange(n_g)[::-1]
    for d in range(n_d):
        iou = ious[d][None, :]
        ok = ~gt_taken & (iou >= thr)
        regular = ok & ~gt_ignore[None, :]
        use = np.where(regular.any(axis=1, keepdims=True), regular, ok & gt_ignore[None, :])
        found = use.any(axis=1)
        if not found.any():
            continue
        vals = np.where(use, iou, -1.0)
        best = vals.max(axis=1, keepdims=True)
        # the last index of the best value (pycocotools replaces on ties)
        last = n_g - 1 - np.argmax((vals == best)[:, rev] & use[:, rev], axis=1)
        t_idx = rows[found]
        g_idx = last[found]
        gt_taken[t_idx, g_idx] = True
        dt_matched[t_idx, d] = True
        dt_ignored[t_idx, d] = gt_ignore[g_idx]
    return dt_matched, dt_ignored


def evaluate_detections(
    gt_boxes: Sequence[np.ndarray],
    gt_classes: Sequence[np.ndarray],
    det_boxes: Sequence[np.ndarray],
    det_scores: Sequence[np.ndarray],
    det_classes: Sequence[np.ndarray],
    *,
    num_classes: int | None = None,
    gt_ignore: Sequence[np.ndarray] | None = None,
    iou_thresholds: np.ndarray | None = None,
    max_dets: int = COCO_MAX_DETS,
    interpolation: str = "coco101",
) -> MapResult:
    """mAP over a set of images (lists indexed by image; boxes xyxy in any common unit).

    Args:
        gt_boxes, gt_classes: per image (n, 4) and (n,) ground truth.
        det_boxes, det_scores, det_classes: per image (m, 4), (m,), (m,) detections.
        num_classes: number of classes (default: 1 + the largest id seen).
        gt_ignore: per image (n,) bool "ignore" flags (difficult / crowd).
        iou_thresholds: default COCO's 0.5:0.05:0.95.
        max_dets: detections kept per image and class (COCO's maxDets; 100).
        interpolation: ``"coco101"`` (COCO, 101 recall points) or ``"voc07"`` (11 points).
    """
    n_img = len(gt_boxes)
    if not (len(gt_classes) == len(det_boxes) == len(det_scores) == len(det_classes) == n_img):
        raise ValueError("all per-image lists must have the same length")
    if interpolation not in ("coco101", "voc07"):
        raise ValueError(f"interpolation must be 'coco101' or 'voc07', not {interpolation!r}")
    thresholds = COCO_IOU_THRESHOLDS if iou_thresholds is None else np.asarray(iou_thresholds,
                                                                                float)
    rec_thr = COCO_RECALL_THRESHOLDS if interpolation == "coco101" else VOC07_RECALL_THRESHOLDS
    gtb = [np.asarray(b, np.float64).reshape(-1, 4) for b in gt_boxes]
    gtc = [np.asarray(c, np.int64).reshape(-1) for c in gt_classes]
    dtb = [np.asarray(b, np.float64).reshape(-1, 4) for b in det_boxes]
    dts = [np.asarray(s, np.float64).reshape(-1) for s in det_scores]
    dtc = [np.asarray(c, np.int64).reshape(-1) for c in det_classes]
    gti = ([np.zeros(len(c), bool) for c in gtc] if gt_ignore is None
           else [np.asarray(g, bool).reshape(-1) for g in gt_ignore])
    if num_classes is None:
        seen = [c.max() for c in gtc + dtc if len(c)]
        num_classes = int(max(seen)) + 1 if seen else 0
    n_t, n_r = len(thresholds), len(rec_thr)
    precision = -np.ones((n_t, n_r, num_classes))
    recall = -np.ones((n_t, num_classes))
    num_gt = np.zeros(num_classes, np.int64)

    # per class: scores, matched, ignored over all images (image order, then score order)
    per_class = [([], [], []) for _ in range(num_classes)]
    for i in range(n_img):
        for k in np.union1d(gtc[i], dtc[i]):
            k = int(k)
            if not 0 <= k < num_classes:
                continue
            g = gtc[i] == k
            gb, gig = gtb[i][g], gti[i][g]
            order_g = np.argsort(gig, kind="mergesort")  # regular ones first
            gb, gig = gb[order_g], gig[order_g]
            num_gt[k] += int(np.sum(~gig))
            d = np.flatnonzero(dtc[i] == k)
            order_d = np.argsort(-dts[i][d], kind="mergesort")[:max_dets]
            d = d[order_d]
            matched, ignored = _match(box_iou_np(dtb[i][d], gb), gig, thresholds)
            per_class[k][0].append(dts[i][d])
            per_class[k][1].append(matched)
            per_class[k][2].append(ignored)

    for k in range(num_classes):
        scores, matched, ignored = per_class[k]
        if not scores or num_gt[k] == 0:
            continue
        scores = np.concatenate(scores)
        order = np.argsort(-scores, kind="mergesort")
        matched = np.concatenate(matched, axis=1)[:, order]
        ignored = np.concatenate(ignored, axis=1)[:, order]
        tps = matched & ~ignored
        fps = ~matched & ~ignored
        tp_sum = np.cumsum(tps, axis=1).astype(np.float64)
        fp_sum = np.cumsum(fps, axis=1).astype(np.float64)
        for t in range(n_t):
            tp, fp = tp_sum[t], fp_sum[t]
            nd = len(tp)
            rc = tp / num_gt[k]
            pr = tp / (fp + tp + np.spacing(1))
            recall[t, k] = rc[-1] if nd else 0.0
            q = np.zeros(n_r)
            if nd:
                pr = np.maximum.accumulate(pr[::-1])[::-1]  # monotone envelope
                inds = np.searchsorted(rc, rec_thr, side="left")
                valid = inds < nd
                q[valid] = pr[inds[valid]]
            precision[t, :, k] = q

    has_gt = num_gt > 0
    ap = np.full((num_classes, n_t), np.nan)
    ap[has_gt] = precision[:, :, has_gt].mean(axis=1).T

    def mean_at(t_mask):
        p = precision[t_mask]
        p = p[p > -1]
        return float(np.mean(p)) if p.size else -1.0

    def at(value):
        return np.isclose(thresholds, value, atol=1e-12)

    return MapResult(
        map50=mean_at(at(0.5)) if at(0.5).any() else float("nan"),
        map50_95=mean_at(np.ones(n_t, bool)),
        map75=mean_at(at(0.75)) if at(0.75).any() else float("nan"),
        ap=ap, precision=precision, recall=recall, iou_thresholds=np.asarray(thresholds),
        num_gt=num_gt,
    )


def fitness(result: MapResult | dict, metric: str = "map50_95") -> float:
    """The model-selection score: ``map50_95``, ``map50`` or YOLOv5's
    ``fitness = 0.1 * map50 + 0.9 * map50_95``."""
    get = (lambda k: result[k]) if isinstance(result, dict) else (lambda k: getattr(result, k))
    if metric == "fitness":
        return 0.1 * float(get("map50")) + 0.9 * float(get("map50_95"))
    if metric not in ("map50", "map50_95"):
        raise ValueError(f"unknown selection metric {metric!r}")
    return float(get(metric))


def evaluate_predictions(records, detections, num_classes: int,
                         max_dets: int = COCO_MAX_DETS,
                         interpolation: str = "coco101") -> MapResult:
    """mAP of per-record detections against the records' ground truth (difficult = ignore).

    ``records``: :class:`~uavcal_jax.data.detection_records.DetectionRecord` s; ``detections``: per
    record ``(boxes (m, 4), scores (m,), classes (m,))`` in the same pixels, e.g.
    :func:`~uavcal_jax.detect.predict.predict_dataset`'s.
    """
    return evaluate_detections(
        [r.boxes for r in records], [r.classes for r in records],
        [d[0] for d in detections], [d[1] for d in detections], [d[2] for d in detections],
        num_classes=num_classes, gt_ignore=[r.difficult for r in records], max_dets=max_dets,
        interpolation=interpolation)
