"""YOLOv5n-like CSP backbone (ultralytics/yolov5 v7.0 ``models/yolov5n.yaml``, depth 0.33,
width 0.25): Conv 6x6/2 stem, Conv 3x3/2 + C3 stages, SPPF. Returns the P3/8, P4/16 and P5/32
features (64, 128, 256 channels at width 0.25)."""

from __future__ import annotations

import math

import flax.linen as nn

from uavcal_jax.detect.config import BN_EPS, BN_MOMENTUM
from uavcal_jax.detect.layers import C3, SPPF, Conv


def _width(c: int, width: float) -> int:
    return int(math.ceil(c * width / 8) * 8)  # YOLOv5 make_divisible(c * gw, 8)


def _depth(n: int, depth: float) -> int:
    return max(round(n * depth), 1) if n > 1 else n


class CSPBackbone(nn.Module):
    depth_multiple: float = 0.33
    width_multiple: float = 0.25
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        w = lambda c: _width(c, self.width_multiple)  # noqa: E731
        d = lambda n: _depth(n, self.depth_multiple)  # noqa: E731
        x = Conv(w(64), 6, 2, 2, name="b0", **bn)(x, train)  # P1/2
        x = Conv(w(128), 3, 2, name="b1", **bn)(x, train)  # P2/4
        x = C3(w(128), d(3), name="b2", **bn)(x, train)
        x = Conv(w(256), 3, 2, name="b3", **bn)(x, train)  # P3/8
        p3 = C3(w(256), d(6), name="b4", **bn)(x, train)
        x = Conv(w(512), 3, 2, name="b5", **bn)(p3, train)  # P4/16
        p4 = C3(w(512), d(9), name="b6", **bn)(x, train)
        x = Conv(w(1024), 3, 2, name="b7", **bn)(p4, train)  # P5/32
        x = C3(w(1024), d(3), name="b8", **bn)(x, train)
        p5 = SPPF(w(1024), 5, name="b9", **bn)(x, train)
        return p3, p4, p5
