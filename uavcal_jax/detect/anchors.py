"""Anchors: YOLOv5 v7.0's ``utils/autoanchor.py`` in NumPy/SciPy.

:func:`anchor_metrics` gives the best possible recall (the fraction of labels that some
anchor can be assigned to under the ``anchor_t`` ratio rule) and the anchors-above-threshold
count; :func:`kmeans_anchors` fits ``n`` anchors to label sizes (k-means on whitened sizes,
then a mutation-selection "evolution" of the anchor fitness, as YOLOv5 does);
:func:`check_anchors` keeps a config's anchors when their best possible recall is at least
0.98 and otherwise replaces them with k-means anchors (when those are better).
Sizes are ``(w, h)`` in pixels of the network input (letterboxed images).
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.detect.config import DetectorConfig


def _ratio_metric(k: np.ndarray, wh: np.ndarray) -> np.ndarray:
    """(n_labels, n_anchors) ``min(r, 1/r)`` over w and h, the worse of the two."""
    r = wh[:, None] / k[None]
    return np.minimum(r, 1.0 / r).min(2)


def anchor_metrics(anchors, wh, anchor_t: float = 4.0) -> tuple[float, float]:
    """``(bpr, aat)``: best possible recall and mean anchors above threshold per label."""
    k = np.asarray(anchors, np.float64).reshape(-1, 2)
    wh = np.asarray(wh, np.float64).reshape(-1, 2)
    if len(wh) == 0:
        return 1.0, 0.0
    x = _ratio_metric(k, wh)
    thr = 1.0 / anchor_t
    best = x.max(1)
    return float((best > thr).mean()), float((x > thr).sum(1).mean())


def _fitness(k, wh, thr):
    best = _ratio_metric(k, wh).max(1)
    return float((best * (best > thr)).mean())


def kmeans_anchors(wh, n: int = 9, anchor_t: float = 4.0, gen: int = 1000,
                   seed: int = 0) -> np.ndarray:
    """``n`` anchors ``(n, 2)`` sorted by area, fitted to label sizes ``wh (m, 2)`` pixels.

    As YOLOv5: labels under 2 px are dropped, k-means (SciPy) on sizes divided by their
    standard deviation, then ``gen`` generations of multiplicative mutations (probability
    0.9, sigma 0.1) kept when they raise the fitness ``mean(best * (best > 1/anchor_t))``.
    """
    from scipy.cluster.vq import kmeans

    rng = np.random.default_rng(seed)
    wh = np.asarray(wh, np.float64).reshape(-1, 2)
    wh = wh[(wh >= 2.0).any(1)]
    if len(wh) < n:
        raise ValueError(f"need at least {n} labels of 2+ pixels for {n} anchors, got {len(wh)}")
    thr = 1.0 / anchor_t
    s = wh.std(0)
    s = np.where(s > 0, s, 1.0)
    k, _ = kmeans(wh / s, n, iter=30, seed=seed)
    if len(k) != n:  # k-means dropped empty clusters: fall back to random sizes
        k = np.sort(rng.random((n, 2)) * wh.max(0) / s, 0)
    k = k * s
    f = _fitness(k, wh, thr)
    mp, sigma = 0.9, 0.1
    for _ in range(gen):
        v = np.ones_like(k)
        while (v == 1).all():
            v = ((rng.random(k.shape) < mp) * rng.random() * rng.standard_normal(k.shape)
                 * sigma + 1).clip(0.3, 3.0)
        kg = (k * v).clip(min=2.0)
        fg = _fitness(kg, wh, thr)
        if fg > f:
            f, k = fg, kg
    return k[np.argsort(k.prod(1))]


def label_sizes(dataset, img_size: tuple[int, int]) -> np.ndarray:
    """(M, 2) widths and heights of all of ``dataset``'s boxes in network-input pixels after
    letterboxing each image into ``img_size`` = (H, W) (what the anchors are matched to)."""
    h, w = img_size
    sizes = [(r.boxes[:, 2:4] - r.boxes[:, 0:2]) * min(w / r.width, h / r.height)
             for r in dataset.records if len(r.boxes)]
    return np.concatenate(sizes).astype(np.float64) if sizes else np.zeros((0, 2))


def check_anchors(config: DetectorConfig, wh, gen: int = 1000, seed: int = 0,
                  min_bpr: float = 0.98) -> tuple[DetectorConfig, dict]:
    """``config`` with anchors that fit the labels: unchanged when their best possible
    recall is at least ``min_bpr``, else k-means anchors if they recall more. Returns the
    config and a report ``{"bpr", "aat", "replaced", "bpr_new"}``."""
    bpr, aat = anchor_metrics(config.anchors, wh, config.anchor_t)
    report = {"bpr": bpr, "aat": aat, "replaced": False}
    if bpr >= min_bpr:
        return config, report
    na = config.num_levels * config.num_anchors
    k = kmeans_anchors(wh, na, config.anchor_t, gen, seed)
    bpr_new, _ = anchor_metrics(k, wh, config.anchor_t)
    report["bpr_new"] = bpr_new
    if bpr_new > bpr:
        anchors = tuple(
            tuple((round(float(w), 2), round(float(h), 2))
                  for w, h in k[i * config.num_anchors:(i + 1) * config.num_anchors])
            for i in range(config.num_levels)
        )
        config = config.replace(anchors=anchors)
        report["replaced"] = True
    return config, report
