"""Target detection: YZNet (RPEOD) and YOLOv5n-like backbones under a YOLOv5 v7.0 head.

Configurations (:mod:`.config`), models, loss, box ops, decoding, NMS and prediction; data
sets, augmentation, metrics, training, the run folder and export.
"""

from uavcal_jax.detect.anchors import anchor_metrics, check_anchors, kmeans_anchors
from uavcal_jax.detect.boxes import bbox_ciou, box_iou
from uavcal_jax.detect.config import (
    EVAL_PREDICT,
    SERVE_PREDICT,
    YOLOV5_ANCHORS,
    DetectConfig,
    DetectorConfig,
    PredictConfig,
    TrainConfig,
)
from uavcal_jax.detect.decode import decode
from uavcal_jax.detect.loss import yolo_loss
from uavcal_jax.detect.model import build_detector, init_detector
from uavcal_jax.detect.nms import Detections, nms, postprocess
from uavcal_jax.detect.predict import (
    ImageDetections,
    detect_images,
    make_predict_fn,
    predict,
)

__all__ = [
    "EVAL_PREDICT",
    "SERVE_PREDICT",
    "YOLOV5_ANCHORS",
    "DetectConfig",
    "DetectorConfig",
    "Detections",
    "ImageDetections",
    "PredictConfig",
    "TrainConfig",
    "anchor_metrics",
    "bbox_ciou",
    "box_iou",
    "build_detector",
    "check_anchors",
    "decode",
    "detect_images",
    "init_detector",
    "kmeans_anchors",
    "make_predict_fn",
    "nms",
    "postprocess",
    "predict",
    "yolo_loss",
]
