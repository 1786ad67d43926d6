"""The static-shape YOLOv5 loss: hand-computed assignment, a dynamic-shape NumPy port of
v7.0 ``ComputeLoss``/``build_targets``, monotonicity and edge cases."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from uavcal_jax.detect.config import DetectorConfig
from uavcal_jax.detect.loss import build_targets_level, yolo_loss


def _sig(x):
    return 1.0 / (1.0 + np.exp(-x))


def _bce(x, y):
    return np.maximum(x, 0) - x * y + np.log1p(np.exp(-np.abs(x)))


def _ciou_np(p, t, eps=1e-7):
    """v7.0 bbox_iou(CIoU=True) on xywh rows, float64."""
    (x1, y1, w1, h1), (x2, y2, w2, h2) = p.T, t.T
    b1x1, b1x2, b1y1, b1y2 = x1 - w1 / 2, x1 + w1 / 2, y1 - h1 / 2, y1 + h1 / 2
    b2x1, b2x2, b2y1, b2y2 = x2 - w2 / 2, x2 + w2 / 2, y2 - h2 / 2, y2 + h2 / 2
    inter = np.clip(np.minimum(b1x2, b2x2) - np.maximum(b1x1, b2x1), 0, None) * np.clip(
        np.minimum(b1y2, b2y2) - np.maximum(b1y1, b2y1), 0, None
    )
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    cw = np.maximum(b1x2, b2x2) - np.minimum(b1x1, b2x1)
    ch = np.maximum(b1y2, b2y2) - np.minimum(b1y1, b2y1)
    c2 = cw**2 + ch**2 + eps
    rho2 = ((b2x1 + b2x2 - b1x1 - b1x2) ** 2 + (b2y1 + b2y2 - b1y1 - b1y2) ** 2) / 4
    v = 4 / math.pi**2 * (np.arctan(w2 / h2) - np.arctan(w1 / h1)) ** 2
    alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


def reference_loss(outputs, targets, cfg: DetectorConfig):
    """NumPy port of YOLOv5 v7.0 ComputeLoss (dynamic shapes, float64).

    ``targets``: (B, T, 6) padded rows -> converted to v7.0's (image, class, x, y, w, h)
    normalised rows. Objectness duplicates keep the maximum IoU (see loss.py).
    """
    outputs = [np.asarray(o, np.float64) for o in outputs]
    h_img, w_img = cfg.img_size
    rows = []
    for b in range(targets.shape[0]):
        for t in targets[b]:
            if t[0] > 0.5:
                rows.append([b, t[1], t[2] / w_img, t[3] / h_img, t[4] / w_img, t[5] / h_img])
    tg = np.array(rows, np.float64).reshape(-1, 6)
    na, nt, nc = 3, tg.shape[0], cfg.num_classes
    ai = np.repeat(np.arange(na, dtype=np.float64)[:, None], nt, 1)
    tga = np.concatenate([np.repeat(tg[None], na, 0), ai[..., None]], 2)  # (na, nt, 7)
    g = 0.5
    off = np.array([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], np.float64) * g
    box_g, obj_g, cls_g = cfg.scaled_gains()
    lbox = lobj = lcls = 0.0
    for i, p in enumerate(outputs):
        bsz, ny, nx, _, _ = p.shape
        anchors = np.array(cfg.anchors[i], np.float64) / cfg.strides[i]
        gain = np.array([1, 1, nx, ny, nx, ny, 1], np.float64)
        t = tga * gain
        if nt:
            r = t[..., 4:6] / anchors[:, None]
            j = np.maximum(r, 1 / r).max(2) < cfg.anchor_t
            t = t[j]
            gxy = t[:, 2:4]
            gxi = np.array([nx, ny]) - gxy
            jj, kk = ((gxy % 1 < g) & (gxy > 1)).T
            ll, mm = ((gxi % 1 < g) & (gxi > 1)).T
            sel = np.stack((np.ones_like(jj), jj, kk, ll, mm))
            t = np.repeat(t[None], 5, 0)[sel]
            offsets = (np.zeros_like(gxy)[None] + off[:, None])[sel]
        else:
            t = tga[0]
            offsets = 0
        b = t[:, 0].astype(int)
        c = t[:, 1].astype(int)
        gxy, gwh, a = t[:, 2:4], t[:, 4:6], t[:, 6].astype(int)
        gij = np.trunc(gxy - offsets).astype(int)
        gi, gj = np.clip(gij[:, 0], 0, nx - 1), np.clip(gij[:, 1], 0, ny - 1)
        tbox = np.concatenate([gxy - gij, gwh], 1)
        tobj = np.zeros((bsz, ny, nx, na))
        n = len(b)
        if n:
            ps = p[b, gj, gi, a]
            pxy = _sig(ps[:, :2]) * 2 - 0.5
            pwh = (_sig(ps[:, 2:4]) * 2) ** 2 * anchors[a]
            iou = _ciou_np(np.concatenate([pxy, pwh], 1), tbox)
            lbox += (1.0 - iou).mean()
            for q in range(n):
                tobj[b[q], gj[q], gi[q], a[q]] = max(tobj[b[q], gj[q], gi[q], a[q]],
                                                     max(iou[q], 0.0))
            if nc > 1:
                tc = np.zeros((n, nc))
                tc[np.arange(n), c] = 1.0
                lcls += _bce(ps[:, 5:], tc).mean()
        lobj += _bce(p[..., 4], tobj).mean() * cfg.balance[i]
    bsz = outputs[0].shape[0]
    lbox, lobj, lcls = lbox * box_g, lobj * obj_g, lcls * cls_g
    return (lbox + lobj + lcls) * bsz, (lbox, lobj, lcls)


def _random_outputs(cfg, bsz, seed):
    rng = np.random.default_rng(seed)
    return tuple(
        rng.normal(0, 1.5, (bsz, h, w, 3, cfg.num_outputs)).astype(np.float32)
        for h, w in cfg.grid_sizes()
    )


def _random_targets(cfg, bsz, t_max, seed, n_per=None):
    rng = np.random.default_rng(seed)
    h, w = cfg.img_size
    tg = np.zeros((bsz, t_max, 6), np.float32)
    for b in range(bsz):
        n = int(rng.integers(0, t_max + 1)) if n_per is None else n_per
        wh = rng.uniform(4, 0.6 * min(h, w), (n, 2))
        cxy = rng.uniform(0, 1, (n, 2)) * (np.array([w, h]) - wh) + wh / 2
        tg[b, :n, 0] = 1
        tg[b, :n, 1] = rng.integers(0, cfg.num_classes, n)
        tg[b, :n, 2:4] = cxy
        tg[b, :n, 4:6] = wh
    return tg


def test_hand_computed_assignment():
    cfg = DetectorConfig(num_classes=2, img_size=(64, 64))
    tg = np.zeros((1, 2, 6), np.float32)
    tg[0, 0] = [1, 1, 19.0, 45.0, 20.0, 28.0]  # second row is padding
    # level 0 (stride 8): gxy (2.375, 5.625), gwh (2.5, 3.5); all three anchors within 4x;
    # x in the left half of its cell -> also the left cell; y in the lower half -> the cell below
    bt = build_targets_level(
        jnp.asarray(tg), (8, 8), jnp.array(cfg.anchors[0]) / 8.0, 8.0, cfg.anchor_t
    )
    mask = np.asarray(bt["mask"])[0, 0]  # (na, 5)
    np.testing.assert_array_equal(mask, np.array([[1, 1, 0, 0, 1]] * 3, bool))
    assert not np.asarray(bt["mask"])[0, 1].any()
    gi, gj = np.asarray(bt["gi"])[0, 0], np.asarray(bt["gj"])[0, 0]
    cells = {(int(gi[o]), int(gj[o])) for o in range(5) if mask[0, o]}
    assert cells == {(2, 5), (1, 5), (2, 6)}
    tbox = np.asarray(bt["tbox"])[0, 0]
    np.testing.assert_allclose(tbox[0], [0.375, 0.625, 2.5, 3.5], atol=1e-6)
    np.testing.assert_allclose(tbox[1], [1.375, 0.625, 2.5, 3.5], atol=1e-6)
    np.testing.assert_allclose(tbox[4], [0.375, -0.375, 2.5, 3.5], atol=1e-6)
    # level 1 (stride 16): gwh (1.25, 1.75); anchors (1.875, 3.81), (3.875, 2.81) match,
    # (3.69, 7.44) does not (7.44 / 1.75 = 4.25 > 4); cells (1,2), left (0,2), below (1,3)
    bt = build_targets_level(
        jnp.asarray(tg), (4, 4), jnp.array(cfg.anchors[1]) / 16.0, 16.0, cfg.anchor_t
    )
    mask = np.asarray(bt["mask"])[0, 0]
    np.testing.assert_array_equal(mask.any(1), [True, True, False])
    np.testing.assert_array_equal(mask[0], [1, 1, 0, 0, 1])
    gi, gj = np.asarray(bt["gi"])[0, 0], np.asarray(bt["gj"])[0, 0]
    assert {(int(gi[o]), int(gj[o])) for o in range(5) if mask[0, o]} == {(1, 2), (0, 2), (1, 3)}
    # level 2 (stride 32): gwh (0.625, 0.875) is more than 4x smaller than every anchor
    bt = build_targets_level(
        jnp.asarray(tg), (2, 2), jnp.array(cfg.anchors[2]) / 32.0, 32.0, cfg.anchor_t
    )
    assert not np.asarray(bt["mask"]).any()


@pytest.mark.parametrize("nc,seed", [(1, 0), (3, 1), (5, 2)])
def test_matches_numpy_port_of_yolov5(nc, seed):
    cfg = DetectorConfig(num_classes=nc, img_size=(96, 128))
    outs = _random_outputs(cfg, 3, seed)
    tg = _random_targets(cfg, 3, 7, seed + 10)
    loss, parts = jax.jit(lambda o, t: yolo_loss(o, t, cfg))(outs, tg)
    ref, (rb, ro, rc) = reference_loss(outs, tg, cfg)
    assert float(loss) == pytest.approx(ref, rel=1e-4)
    assert float(parts["box"]) == pytest.approx(rb, rel=1e-4, abs=1e-7)
    assert float(parts["obj"]) == pytest.approx(ro, rel=1e-4)
    assert float(parts["cls"]) == pytest.approx(rc, rel=1e-4, abs=1e-7)


def test_gains_scaling_follows_train_py():
    cfg = DetectorConfig(num_classes=20, img_size=(320, 320))
    box, obj, cls = cfg.scaled_gains()
    assert box == pytest.approx(0.05)
    assert cls == pytest.approx(0.5 * 20 / 80)
    assert obj == pytest.approx(1.0 * (320 / 640) ** 2)


def test_zero_targets_only_objectness():
    cfg = DetectorConfig(num_classes=3, img_size=(64, 96))
    outs = _random_outputs(cfg, 2, 5)
    tg = np.zeros((2, 4, 6), np.float32)
    loss, parts = yolo_loss(outs, tg, cfg)
    assert float(parts["box"]) == 0.0 and float(parts["cls"]) == 0.0
    expect = sum(_bce(o[..., 4].astype(np.float64), 0.0).mean() * bal
                 for o, bal in zip(outs, cfg.balance, strict=True))
    expect *= cfg.scaled_gains()[1]
    assert float(parts["obj"]) == pytest.approx(expect, rel=1e-5)
    assert float(loss) == pytest.approx(2 * expect, rel=1e-5)
    g = jax.grad(lambda o: yolo_loss(o, tg, cfg)[0])(outs)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def test_padding_rows_are_ignored():
    cfg = DetectorConfig(num_classes=2, img_size=(64, 64))
    outs = _random_outputs(cfg, 1, 7)
    tg = _random_targets(cfg, 1, 3, 8, n_per=3)
    padded = np.zeros((1, 9, 6), np.float32)
    padded[:, :3] = tg
    padded[0, 5] = [0, 1, 30, 30, 10, 10]  # a row with valid = 0 carries no target
    a = yolo_loss(outs, tg, cfg)[0]
    b = yolo_loss(outs, padded, cfg)[0]
    assert float(a) == pytest.approx(float(b), rel=1e-6)


def test_loss_decreases_toward_targets():
    cfg = DetectorConfig(num_classes=2, img_size=(64, 64))
    outs = _random_outputs(cfg, 2, 11)
    tg = _random_targets(cfg, 2, 4, 12, n_per=3)
    opt = optax.adam(0.1)
    state = opt.init(outs)

    @jax.jit
    def step(o, st):
        val, g = jax.value_and_grad(lambda o: yolo_loss(o, tg, cfg)[0])(o)
        upd, st = opt.update(g, st)
        return optax.apply_updates(o, upd), st, val

    losses = []
    for _ in range(60):  # move the raw outputs toward the targets
        outs, state, val = step(outs, state)
        losses.append(float(val))
    assert losses[-1] < 0.2 * losses[0]
    assert losses[-1] < losses[30] < losses[0]


def test_compiles_once_for_new_targets():
    cfg = DetectorConfig(num_classes=2, img_size=(64, 64))
    traces = []

    @jax.jit
    def f(o, t):
        traces.append(1)
        return yolo_loss(o, t, cfg)[0]

    outs = _random_outputs(cfg, 2, 0)
    for s in range(3):
        f(outs, _random_targets(cfg, 2, 5, s))
    assert len(traces) == 1
