"""YOLOv5 v7.0 loss (``utils/loss.py:ComputeLoss``) with static shapes, so it jit-compiles once.

Targets are ``(B, T_max, 6)`` rows ``[valid, class, cx, cy, w, h]`` in pixels of the network
input; padded rows have ``valid = 0``. ``build_targets`` becomes a fixed grid of candidate
matches per level: ``(B, T_max, na anchors, 5 offsets)`` with a mask, where

* an anchor matches a target when ``max(r, 1/r) < anchor_t`` for both width and height ratios
  ``r = target_wh / anchor_wh`` (``hyp['anchor_t'] = 4.0``);
* offset 0 is the cell containing the centre; offsets 1-4 are the neighbouring cells left, up,
  right and down, taken when the centre lies in that half of its cell (``g = 0.5``) and not in
  the border cell -- YOLOv5's ``j, k, l, m`` masks, so normally three cells per matched anchor;
* grid indices are ``trunc(gxy - offset)`` clamped to the grid, and the box target is
  ``(gxy - gij, gwh)`` with the unclamped ``gij`` -- as in v7.0.

Per level ``i``: ``lbox += mean(1 - CIoU)`` over the matches; objectness target = the detached
CIoU clamped at 0 at the matched cells (where several matches share a cell and anchor we keep
the largest IoU; PyTorch keeps an unspecified one of them), ``lobj += BCE_mean * balance[i]``;
``lcls += BCE_mean`` over matches x classes with targets ``(cn, cp)`` (only when ``C > 1``).
Finally ``loss = (box * lbox + obj * lobj + cls * lcls) * B`` with the gains of
:meth:`DetectorConfig.scaled_gains`; the returned components are the three gained terms
(YOLOv5's logged ``lbox, lobj, lcls``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.detect.boxes import bbox_ciou
from uavcal_jax.detect.config import DetectorConfig

#: Cell offsets (x, y) times g = 0.5: centre, left, up, right, down (YOLOv5's ``off``).
OFFSETS = jnp.array([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], jnp.float32) * 0.5


def bce_with_logits(logits, targets, pos_weight: float = 1.0):
    """Element-wise ``nn.BCEWithLogitsLoss(pos_weight=...)(reduction='none')``."""
    return pos_weight * targets * jax.nn.softplus(-logits) + (1.0 - targets) * jax.nn.softplus(
        logits
    )


def build_targets_level(targets, grid_hw, anchors_grid, stride: float, anchor_t: float):
    """Candidate matches of one level.

    Args:
        targets: (B, T, 6) ``[valid, cls, cx, cy, w, h]`` in pixels.
        grid_hw: (ny, nx) of this level.
        anchors_grid: (na, 2) anchors in grid units (pixels / stride).
    Returns a dict of arrays: ``mask (B,T,na,5)`` bool, ``gi, gj (B,T,5)`` int32 clamped cell
    indices, ``tbox (B,T,5,4)`` grid-unit ``(x - gi, y - gj, w, h)``, ``cls (B,T)`` int32.
    """
    ny, nx = grid_hw
    valid = targets[..., 0] > 0.5
    gxy = targets[..., 2:4] / stride  # (B,T,2)
    gwh = targets[..., 4:6] / stride
    r = gwh[:, :, None, :] / anchors_grid[None, None, :, :]  # (B,T,na,2)
    rr = jnp.maximum(r, 1.0 / jnp.where(r > 0, r, 1e-30))  # padded rows: no NaN/inf
    match = (jnp.max(rr, axis=-1) < anchor_t) & valid[:, :, None]  # (B,T,na)

    g = 0.5
    gain = jnp.array([nx, ny], jnp.float32)
    gxi = gain - gxy
    jk = (jnp.mod(gxy, 1.0) < g) & (gxy > 1.0)  # (B,T,2): j (x), k (y)
    lm = (jnp.mod(gxi, 1.0) < g) & (gxi > 1.0)  # l (x), m (y)
    offmask = jnp.stack(
        [jnp.ones_like(jk[..., 0]), jk[..., 0], jk[..., 1], lm[..., 0], lm[..., 1]], axis=-1
    )  # (B,T,5)
    mask = match[..., None] & offmask[:, :, None, :]  # (B,T,na,5)

    gij = jnp.trunc(gxy[:, :, None, :] - OFFSETS[None, None])  # (B,T,5,2), .long()
    gi = jnp.clip(gij[..., 0], 0, nx - 1).astype(jnp.int32)
    gj = jnp.clip(gij[..., 1], 0, ny - 1).astype(jnp.int32)
    txy = gxy[:, :, None, :] - gij
    twh = jnp.broadcast_to(gwh[:, :, None, :], txy.shape)
    tbox = jnp.concatenate([txy, twh], axis=-1)
    return {
        "mask": mask,
        "gi": gi,
        "gj": gj,
        "tbox": tbox,
        "cls": targets[..., 1].astype(jnp.int32),
    }


def yolo_loss(outputs, targets, config: DetectorConfig):
    """YOLOv5 v7.0 ``ComputeLoss`` -> ``(loss, {"box", "obj", "cls", "loss"})``.

    Args:
        outputs: tuple of 3 raw head outputs ``(B, H/s, W/s, na, 5 + C)``.
        targets: ``(B, T_max, 6)`` float32 ``[valid, class, cx, cy, w, h]`` in input pixels.
        config: the :class:`DetectorConfig` (anchors, strides, gains, balance, anchor_t).
    """
    targets = jnp.asarray(targets, jnp.float32)
    nc = config.num_classes
    eps_ls = config.label_smoothing
    cp, cn = 1.0 - 0.5 * eps_ls, 0.5 * eps_ls
    box_g, obj_g, cls_g = config.scaled_gains()
    lbox = jnp.zeros((), jnp.float32)
    lobj = jnp.zeros((), jnp.float32)
    lcls = jnp.zeros((), jnp.float32)
    bsz = outputs[0].shape[0]
    dummy_box = jnp.array([0.5, 0.5, 1.0, 1.0], jnp.float32)

    for i, pi in enumerate(outputs):
        pi = pi.astype(jnp.float32)
        b, ny, nx, na, _ = pi.shape
        stride = float(config.strides[i])
        anchors_grid = jnp.array(config.anchors[i], jnp.float32) / stride  # (na,2)
        bt = build_targets_level(targets, (ny, nx), anchors_grid, stride, config.anchor_t)
        mask = bt["mask"]  # (B,T,na,5)
        bidx = jnp.arange(b)[:, None, None, None]
        aidx = jnp.arange(na)[None, None, :, None]
        gj = bt["gj"][:, :, None, :]
        gi = bt["gi"][:, :, None, :]
        ps = pi[bidx, gj, gi, aidx]  # (B,T,na,5,no)

        pxy = jax.nn.sigmoid(ps[..., 0:2]) * 2.0 - 0.5
        pwh = (jax.nn.sigmoid(ps[..., 2:4]) * 2.0) ** 2 * anchors_grid[None, None, :, None, :]
        pbox = jnp.concatenate([pxy, pwh], axis=-1)
        tbox = jnp.broadcast_to(bt["tbox"][:, :, None], pbox.shape)
        tbox = jnp.where(mask[..., None], tbox, dummy_box)
        pbox = jnp.where(mask[..., None], pbox, dummy_box)
        iou = bbox_ciou(pbox, tbox)  # (B,T,na,5)
        mf = mask.astype(jnp.float32)
        n = jnp.sum(mf)
        lbox = lbox + jnp.sum(mf * (1.0 - iou)) / jnp.maximum(n, 1.0)

        # objectness target: detached IoU clamped at 0, scattered to the matched cells
        iou_t = jnp.where(mask, jnp.clip(jax.lax.stop_gradient(iou), 0.0), 0.0)
        shape_idx = (
            jnp.broadcast_to(bidx, mask.shape),
            jnp.broadcast_to(gj, mask.shape),
            jnp.broadcast_to(gi, mask.shape),
            jnp.broadcast_to(aidx, mask.shape),
        )
        tobj = jnp.zeros((b, ny, nx, na), jnp.float32).at[shape_idx].max(iou_t)
        obji = jnp.mean(bce_with_logits(pi[..., 4], tobj, config.obj_pw))
        lobj = lobj + obji * config.balance[i]

        if nc > 1:
            onehot = jax.nn.one_hot(bt["cls"], nc, dtype=jnp.float32)  # (B,T,C)
            tcls = cn + (cp - cn) * onehot
            tcls = jnp.broadcast_to(tcls[:, :, None, None, :], ps[..., 5:].shape)
            bce = jnp.sum(bce_with_logits(ps[..., 5:], tcls, config.cls_pw), axis=-1)
            lcls = lcls + jnp.sum(mf * bce) / (jnp.maximum(n, 1.0) * nc)

    lbox = lbox * box_g
    lobj = lobj * obj_g
    lcls = lcls * cls_g
    loss = (lbox + lobj + lcls) * bsz
    return loss, {"box": lbox, "obj": lobj, "cls": lcls, "loss": loss}
