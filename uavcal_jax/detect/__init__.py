"""Target detection: YZNet (RPEOD) and YOLOv5n-like backbones under a YOLOv5 v7.0 head.

Models, loss, box ops, decoding, NMS and prediction (helper E); data, augmentation, metrics,
training and export (helper F).
"""

from uavcal_jax.detect.anchors import anchor_metrics, check_anchors, kmeans_anchors
from uavcal_jax.detect.boxes import bbox_ciou, box_iou, xywh_to_xyxy, xyxy_to_xywh
from uavcal_jax.detect.config import YOLOV5_ANCHORS, DetectorConfig
from uavcal_jax.detect.decode import decode
from uavcal_jax.detect.loss import yolo_loss
from uavcal_jax.detect.model import build_detector, init_detector
from uavcal_jax.detect.nms import Detections, nms, postprocess
from uavcal_jax.detect.predict import make_predict_fn, predict

__all__ = [
    "YOLOV5_ANCHORS",
    "DetectorConfig",
    "Detections",
    "anchor_metrics",
    "bbox_ciou",
    "box_iou",
    "build_detector",
    "check_anchors",
    "decode",
    "init_detector",
    "kmeans_anchors",
    "make_predict_fn",
    "nms",
    "postprocess",
    "predict",
    "xywh_to_xyxy",
    "xyxy_to_xywh",
    "yolo_loss",
]
