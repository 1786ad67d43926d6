"""The detectors: backbone (YZNet or YOLOv5n-like CSP) -> PANet neck -> YOLOv5 Detect head.

``build_detector(config)`` returns a Flax module; ``module.apply(variables, images,
train=False)`` maps images ``(B, H, W, 3)`` float32 in ``[0, 1]`` to a tuple of three raw
outputs ``(B, H/s, W/s, 3, 5 + C)`` for s = 8, 16, 32 (logits: x, y, w, h, obj, classes).
With ``train=True`` pass ``mutable=["batch_stats"]`` to update the BN running statistics.

The variants (RPEOD Table 3 names the two YZNet models but not their neck widths):

* ``yznet-yolo``: YZNet taps (24, 80, 120 channels at strides 8, 16, 32), an SPPF on the
  stride-32 tap (YOLOv5 puts one at the end of every backbone), then YOLOv5n's PANet neck
  (outputs 64, 128, 256 channels, one bottleneck per C3) and the Detect head;
* ``yznet-yolo-tiny``: the same with the neck halved (32, 64, 128);
* ``yolov5n-like``: YOLOv5n v7.0 exactly (CSP backbone with a 6x6 stem, C3 blocks and SPPF;
  the same neck as ``yznet-yolo``) -- the baseline a user would otherwise pick.

Counts and speeds are in :mod:`uavcal_jax.detect.yznet`'s docstring and
``experiments/bench_detector.py``.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.detect.config import DetectorConfig
from uavcal_jax.detect.csp import CSPBackbone
from uavcal_jax.detect.head import DetectHead
from uavcal_jax.detect.layers import SPPF
from uavcal_jax.detect.neck import PANNeck
from uavcal_jax.detect.yznet import TAP_CHANNELS, YZNetBackbone


class Detector(nn.Module):
    config: DetectorConfig

    @nn.compact
    def __call__(self, images, train: bool = False):
        cfg = self.config
        bn = dict(bn_momentum=cfg.bn_momentum, bn_eps=cfg.bn_eps)
        x = images.astype(jnp.float32)
        if cfg.model == "yolov5n-like":
            feats = CSPBackbone(name="backbone", **bn)(x, train)
        else:
            c3, c4, c5 = YZNetBackbone(dw_impl=cfg.dw_impl, name="backbone", **bn)(x, train)
            c5 = SPPF(TAP_CHANNELS[2], 5, name="sppf", **bn)(c5, train)
            feats = (c3, c4, c5)
        feats = PANNeck(cfg.widths, cfg.depth, name="neck", **bn)(feats, train)
        return DetectHead(cfg.num_classes, cfg.strides, cfg.num_anchors, name="head")(feats)


def build_detector(config: DetectorConfig) -> Detector:
    return Detector(config)


def init_detector(key: jax.Array, config: DetectorConfig, batch_size: int = 1) -> dict:
    """``{"params", "batch_stats"}`` for ``config``.

    The variables do not depend on the input size, so the model is traced on a small
    ``(batch_size, 64, 64, 3)`` zero batch, and the init function is compiled with XLA's
    backend optimisation off: it runs once, and hundreds of separate random draws otherwise
    take XLA:CPU 15-30 s to optimise (about half that at level 0).
    """
    dummy = jnp.zeros((batch_size, 64, 64, 3), jnp.float32)
    init = jax.jit(lambda k, x: build_detector(config).init(k, x, train=False))
    try:
        compiled = init.lower(key, dummy).compile(
            compiler_options={"xla_backend_optimization_level": 0}
        )
    except Exception:  # a backend without that option: the default compilation
        compiled = init
    variables = compiled(key, dummy)
    return {"params": variables["params"], "batch_stats": variables["batch_stats"]}
