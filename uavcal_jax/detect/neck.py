"""YOLOv5 v7.0 PANet neck (the ``head:`` section of ``models/yolov5n.yaml``) with configurable
widths: top-down FPN (1x1 lateral conv, nearest 2x upsample, concat, C3 without shortcut),
then bottom-up PAN (3x3/2 conv, concat with the lateral, C3). ``widths = (w3, w4, w5)`` are the
output channels at strides 8, 16, 32; YOLOv5n uses (64, 128, 256).
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from uavcal_jax.detect.config import BN_EPS, BN_MOMENTUM
from uavcal_jax.detect.layers import C3, Conv, upsample2


class PANNeck(nn.Module):
    widths: tuple[int, int, int] = (64, 128, 256)
    depth: int = 1
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, feats, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        c3, c4, c5 = feats
        w3, w4, w5 = self.widths
        n = self.depth
        lat5 = Conv(w4, 1, 1, name="lat5", **bn)(c5, train)  # yaml #10
        x = jnp.concatenate([upsample2(lat5), c4], -1)  # 11, 12
        x = C3(w4, n, shortcut=False, name="td4", **bn)(x, train)  # 13
        lat4 = Conv(w3, 1, 1, name="lat4", **bn)(x, train)  # 14
        x = jnp.concatenate([upsample2(lat4), c3], -1)  # 15, 16
        p3 = C3(w3, n, shortcut=False, name="out3", **bn)(x, train)  # 17 (P3/8)
        x = Conv(w3, 3, 2, name="down3", **bn)(p3, train)  # 18
        x = jnp.concatenate([x, lat4], -1)  # 19
        p4 = C3(w4, n, shortcut=False, name="out4", **bn)(x, train)  # 20 (P4/16)
        x = Conv(w4, 3, 2, name="down4", **bn)(p4, train)  # 21
        x = jnp.concatenate([x, lat5], -1)  # 22
        p5 = C3(w5, n, shortcut=False, name="out5", **bn)(x, train)  # 23 (P5/32)
        return p3, p4, p5
