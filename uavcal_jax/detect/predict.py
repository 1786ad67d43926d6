"""Inference as one pure jitted function: images -> network -> decode -> NMS."""

from __future__ import annotations

import jax

from uavcal_jax.detect.config import DetectorConfig
from uavcal_jax.detect.model import build_detector
from uavcal_jax.detect.nms import Detections, postprocess


def predict(
    variables,
    images,
    config: DetectorConfig,
    conf_thresh: float = 0.25,
    iou_thresh: float = 0.45,
    max_det: int = 300,
    multi_label: bool = False,
    pre_nms_topk: int = 1000,
) -> Detections:
    """Un-jitted predict: ``images (B, H, W, 3)`` float32 in [0, 1] -> :class:`Detections`."""
    outputs = build_detector(config).apply(variables, images, train=False)
    return postprocess(
        outputs,
        config,
        conf_thresh,
        iou_thresh,
        max_det,
        multi_label=multi_label,
        pre_nms_topk=pre_nms_topk,
    )


def make_predict_fn(
    config: DetectorConfig,
    conf_thresh: float = 0.25,
    iou_thresh: float = 0.45,
    max_det: int = 300,
    multi_label: bool = False,
    pre_nms_topk: int = 1000,
):
    """A jitted ``fn(variables, images) -> Detections`` (variables: params + batch_stats)."""

    def fn(variables, images):
        return predict(
            {"params": variables["params"], "batch_stats": variables["batch_stats"]},
            images,
            config,
            conf_thresh,
            iou_thresh,
            max_det,
            multi_label,
            pre_nms_topk,
        )

    return jax.jit(fn)
