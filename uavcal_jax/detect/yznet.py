"""YZNet (RPEOD, Zhang et al., Machines 2022, 10, 181, section 4, Table 1) in Flax.

Architecture (224x224 input)
----------------------------
The issue gives Table 1's columns: a 3x3 stride-2 stem to 16 channels, then eleven inverted
residual blocks with kernel sizes 3 or 5, expansion factors
``(1, 4.5, 3.7, 4, 5, 6, 4, 4, 6, 6, 6)`` and output channels
``(16, 24, 24, 40, 40, 60, 60, 80, 80, 100, 120)``; then a 1x1 convolution to 600, global
average pooling, a fully connected layer of 1,200 and a 20-way classifier. The expansion
factors are MobileNetV3-Small's (Howard et al. 2019, Table 2: 16/16, 72/16 = 4.5,
88/24 = 3.67, 96/24 = 4, then 6, 6, 3, 3, 6, 6, 6) with two factors changed and wider outputs,
so the rows not given explicitly (kernel size, SE, activation, stride) follow MobileNetV3-Small
row by row:

====  ======  =====  ======  ======  ===  =====  ======  ============
 row  input   k      exp     hidden  out  SE     act     stride
====  ======  =====  ======  ======  ===  =====  ======  ============
stem  224x3   3      -       -       16   -      HS      2 -> 112
  1   112x16  3      1       16      16   yes    RE      2 -> 56
  2   56x16   3      4.5     72      24   -      RE      2 -> 28
  3   28x24   3      3.7     88      24   -      RE      1      (P3/8)
  4   28x24   5      4       96      40   yes    HS      2 -> 14
  5   14x40   5      5       200     40   yes    HS      1
  6   14x40   5      6       240     60   yes    HS      1
  7   14x60   5      4       240     60   yes    HS      1
  8   14x60   5      4       240     80   yes    HS      1      (P4/16)
  9   14x80   5      6       480     80   yes    HS      2 -> 7
 10   7x80    5      6       480     100  yes    HS      1
 11   7x100   5      6       600     120  yes    HS      1      (P5/32)
head  7x120   1      -       -       600  -      HS      1, then avg pool
      1x600   FC 1,200 (HS), FC 20
====  ======  =====  ======  ======  ===  =====  ======  ============

Hidden channels are ``make_divisible(in * exp, 8)`` (MobileNet's rounding): every product is
already a multiple of 8 except 24 x 3.7 = 88.8 -> 88, which is MobileNetV3's 88 (the paper
rounded 88/24 to 3.7). SE squeezes to ``make_divisible(hidden / 4, 8)`` channels, with ReLU and
a hard sigmoid gate (section 4.1). Every projection is linear (no activation after the BN) and
identity shortcuts are used where the stride is 1 and the channels match (blocks 3, 5 and 7;
section 4.4). BN everywhere except the classifier's FC layers, as in MobileNetV3 (there the
two last layers are "NBN").

The strides give the feature sizes 112, 56, 28, 28, 14, ..., 14, 7, 7, 7 from 224x224, so the
detector taps block 3 (stride 8, 24 ch), block 8 (stride 16, 80 ch) and block 11 (stride 32,
120 ch) -- the same positions MobileNetV3-Small's detection heads use.

Counts (``uavcal_jax.detect.counting``; printed by ``experiments/bench_detector.py``)
-----------------------------------------------------------------------------------------
Classification YZNet, 224x224, 20 classes:

* **parameters: 1,840,516** (BN scale/bias included: 13,496 of them) against the paper's
  "about 1.74 M": **+5.8 %**, inside the 10 % tolerance. Where they are: the FC 600 -> 1,200
  layer alone holds 721,200, the 1x1 head conv 73,200, the classifier 24,020, the eleven
  blocks 1,021,632 -- of which squeeze-excitation is 532,280 (blocks 9-11 alone 415k).
  The paper does not print SE placement or squeeze width; the ~100 k difference is of the
  size of one SE choice (e.g. squeezing 600 -> 152 -> 600 in block 11 is 183 k) or of the
  FC biases plus BN parameters, which some counters leave out.
* **multiply-adds: 70.5 M** (7.05e7) against the paper's 5.9e7 (+19 %): pointwise 1x1
  convolutions 51.8 M, depthwise 8.5 M, stem 5.4 M, head conv + FC layers 4.3 M, SE 0.53 M.
  Without the depthwise layers the count is 62.0 M, about 5 % above the paper, so the paper
  probably counted only the dense (1x1/3x3 full) multiplications or used a narrower variant;
  our count includes every convolution and FC layer and excludes BN, activations and the SE
  rescaling (MobileNet's "MAdds" convention).

Detectors at 640x480 (5 classes; parameters / GFLOPs = 2 x multiply-adds): YZNet-YOLO-tiny
1,244,274 / 1.09, YZNet-YOLO 1,756,658 / 1.81, YOLOv5n-like 1,770,682 / 3.11. With 80
classes at 640x640 the YOLOv5n-like model has 1,872,157 parameters and 4.47 GFLOPs: YOLOv5's
own model summary of ``yolov5n.yaml`` prints 1,872,157 parameters and 4.6 GFLOPs (thop, which
also counts BN and other small layers), and its README lists 4.5 GFLOPs.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from uavcal_jax.detect.config import BN_EPS, BN_MOMENTUM
from uavcal_jax.detect.layers import (
    ConvBNAct,
    Dense,
    InvertedResidual,
    hardswish,
    make_divisible,
)

#: Table 1 rows: (kernel, expansion, out channels, SE, activation, stride).
YZNET_BLOCKS: tuple[tuple[int, float, int, bool, str, int], ...] = (
    (3, 1.0, 16, True, "relu", 2),
    (3, 4.5, 24, False, "relu", 2),
    (3, 3.7, 24, False, "relu", 1),
    (5, 4.0, 40, True, "hswish", 2),
    (5, 5.0, 40, True, "hswish", 1),
    (5, 6.0, 60, True, "hswish", 1),
    (5, 4.0, 60, True, "hswish", 1),
    (5, 4.0, 80, True, "hswish", 1),
    (5, 6.0, 80, True, "hswish", 2),
    (5, 6.0, 100, True, "hswish", 1),
    (5, 6.0, 120, True, "hswish", 1),
)
STEM_CHANNELS = 16
#: Indices (0-based) of the blocks whose outputs feed the detector: strides 8, 16, 32.
TAPS = (2, 7, 10)
#: Channels of the three taps.
TAP_CHANNELS = (24, 80, 120)
HEAD_CONV = 600
HEAD_FC = 1200

def block_hidden(cin: int, expansion: float) -> int:
    return make_divisible(cin * expansion, 8)


class YZNetBackbone(nn.Module):
    """Stem + the eleven blocks; returns the three taps (strides 8, 16, 32) or all features."""

    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS
    dw_impl: str = "shift"

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        x = ConvBNAct(STEM_CHANNELS, 3, 2, "hswish", name="stem", **bn)(x, train)
        taps = []
        cin = STEM_CHANNELS
        for i, (k, e, out, se, act, s) in enumerate(YZNET_BLOCKS):
            x = InvertedResidual(
                hidden=block_hidden(cin, e),
                out=out,
                kernel_size=k,
                stride=s,
                use_se=se,
                act=act,
                dw_impl=self.dw_impl,
                name=f"block{i + 1}",
                **bn,
            )(x, train)
            cin = out
            if i in TAPS:
                taps.append(x)
        return tuple(taps)


class YZNetClassifier(nn.Module):
    """The classification YZNet of Table 1: backbone, 1x1 conv to 600 (BN, HS), global
    average pool, FC 1,200 (HS), FC ``num_classes`` (20). Returns logits."""

    num_classes: int = 20
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS
    dw_impl: str = "shift"

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        _, _, x = YZNetBackbone(dw_impl=self.dw_impl, name="backbone", **bn)(x, train)
        x = ConvBNAct(HEAD_CONV, 1, 1, "hswish", name="head_conv", **bn)(x, train)
        x = jnp.mean(x, axis=(1, 2))
        x = hardswish(Dense(HEAD_FC, name="fc")(x))
        return Dense(self.num_classes, name="classifier")(x)
