"""YOLOv5 ``Detect`` head: a 1x1 convolution (with bias) per level to ``na * (5 + C)``
channels, reshaped to ``(B, H/s, W/s, na, 5 + C)`` (channel index ``a * (5 + C) + k`` as in
PyTorch's ``view(bs, na, no, ny, nx)``). Biases are initialised as v7.0's
``Model._initialize_biases``: objectness ``+= log(8 / (640 / s)^2)`` (about 8 objects per
640x640 image), classes ``+= log(0.6 / (C - 0.99))``.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.detect.layers import F32, Conv2D


def _detect_bias_init(fan_in: int, stride: int, na: int, nc: int):
    bound = 1.0 / math.sqrt(fan_in)
    no = 5 + nc

    def init(key, shape, dtype=F32):
        b = jax.random.uniform(key, (na, no), dtype, -bound, bound)
        b = b.at[:, 4].add(math.log(8.0 / (640.0 / stride) ** 2))
        b = b.at[:, 5:].add(math.log(0.6 / (nc - 0.99)))
        return b.reshape(shape)

    return init


class DetectHead(nn.Module):
    num_classes: int
    strides: tuple[int, ...]  # DetectorConfig.strides
    num_anchors: int = 3

    @nn.compact
    def __call__(self, feats):
        na, no = self.num_anchors, 5 + self.num_classes
        outs = []
        for i, (x, s) in enumerate(zip(feats, self.strides, strict=True)):
            y = Conv2D(
                na * no,
                1,
                use_bias=True,
                bias_init=_detect_bias_init(x.shape[-1], s, na, self.num_classes),
                name=f"m_{i}",
            )(x)
            b, h, w, _ = y.shape
            outs.append(y.reshape(b, h, w, na, no).astype(jnp.float32))
        return tuple(outs)
