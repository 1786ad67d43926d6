"""The detector's configurations: the model, how it predicts, and how it is trained.

:class:`DetectorConfig` defines a detector, its decoding and its loss; :class:`PredictConfig`
the post-processing thresholds, with the two presets :data:`EVAL_PREDICT` (YOLOv5 ``val.py``,
for mAP) and :data:`SERVE_PREDICT` (YOLOv5 ``detect.py``, for use); :class:`TrainConfig` a
training run; :class:`DetectConfig` is the root holding a detector and its training run.
Every default lives here; the CLI and the experiments read them from the fields.

The loss gains are YOLOv5's ``hyp.scratch-low.yaml`` values (box 0.05, obj 1.0, cls 0.5);
:meth:`DetectorConfig.scaled_gains` applies the scaling that v7.0's ``train.py`` does before
training (``box *= 3/nl``, ``cls *= nc/80 * 3/nl``, ``obj *= (imgsz/640)**2 * 3/nl``).
Anchors are in pixels of the network input, three (w, h) pairs per level, YOLOv5's defaults
for strides 8, 16 and 32 (``models/yolov5n.yaml``); k-means anchors fitted on training labels
can be passed instead (``anchors=...``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from uavcal_jax.detect.augment import AugmentConfig
from uavcal_jax.detect.metrics import COCO_MAX_DETS

#: YOLOv5's default anchors (pixels), P3/8, P4/16, P5/32.
#: Batch-norm running-average decay (Flax convention: YOLOv5's torch momentum 0.03 is 0.97
#: here) and epsilon (YOLOv5's 1e-3): the defaults of every detector layer.
BN_MOMENTUM, BN_EPS = 0.97, 1e-3
YOLOV5_ANCHORS: tuple[tuple[tuple[float, float], ...], ...] = (
    ((10.0, 13.0), (16.0, 30.0), (33.0, 23.0)),
    ((30.0, 61.0), (62.0, 45.0), (59.0, 119.0)),
    ((116.0, 90.0), (156.0, 198.0), (373.0, 326.0)),
)

#: Detector variants: ``yznet-yolo`` and ``yznet-yolo-tiny`` (RPEOD Table 3) and the
#: YOLOv5n-like CSP baseline.
MODELS = ("yznet-yolo-tiny", "yznet-yolo", "yolov5n-like")

#: PANet neck output widths (P3, P4, P5) and C3 depth per model (see :mod:`.neck`).
NECK_WIDTHS = {
    "yznet-yolo": (64, 128, 256),
    "yznet-yolo-tiny": (32, 64, 128),
    "yolov5n-like": (64, 128, 256),
}
NECK_DEPTH = {"yznet-yolo": 1, "yznet-yolo-tiny": 1, "yolov5n-like": 1}

#: Depthwise-convolution implementations (see :class:`DetectorConfig`).
DW_IMPLS = ("shift", "grouped")


@dataclass(frozen=True)
class DetectorConfig:
    """Everything that defines a detector, its decoding and its loss.

    Attributes:
        model: ``"yznet-yolo-tiny"`` | ``"yznet-yolo"`` | ``"yolov5n-like"``.
        num_classes: number of object classes ``C``; outputs carry ``5 + C`` channels.
        img_size: network input ``(H, W)`` in pixels; both multiples of 32.
        anchors: 3 levels x 3 anchors x (w, h) in input pixels.
        strides: the three output strides (8, 16, 32).
        box_gain, obj_gain, cls_gain: YOLOv5 ``hyp`` gains before v7.0's scaling.
        anchor_t: anchor-multiple threshold of the target assignment (``hyp['anchor_t']``).
        balance: objectness loss weight per level.
        label_smoothing: class label smoothing epsilon (YOLOv5 default 0).
        cls_pw, obj_pw: BCE positive weights (YOLOv5 default 1).
        bn_momentum, bn_eps: batch-norm running-average decay and epsilon
            (:data:`BN_MOMENTUM`, :data:`BN_EPS`).
        neck_widths, neck_depth: override the PANet neck (``None``: the model's default).
        dw_impl: how depthwise convolutions are computed: ``"shift"`` (a sum of k*k shifted,
            per-channel-scaled slices; fastest on XLA:CPU), ``"grouped"`` (a grouped
            ``conv_general_dilated``). Both use the same parameters and agree to 1e-5.
    """

    model: str = "yznet-yolo-tiny"
    num_classes: int = 1
    img_size: tuple[int, int] = (480, 640)
    anchors: tuple[tuple[tuple[float, float], ...], ...] = YOLOV5_ANCHORS
    strides: tuple[int, ...] = (8, 16, 32)
    box_gain: float = 0.05
    obj_gain: float = 1.0
    cls_gain: float = 0.5
    anchor_t: float = 4.0
    balance: tuple[float, ...] = (4.0, 1.0, 0.4)
    label_smoothing: float = 0.0
    cls_pw: float = 1.0
    obj_pw: float = 1.0
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS
    neck_widths: tuple[int, int, int] | None = None
    neck_depth: int | None = None
    dw_impl: str = "shift"

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown detector model {self.model!r}; choose from {MODELS}")
        if self.num_classes < 1:
            raise ValueError("num_classes must be >= 1")
        h, w = self.img_size
        if h % 32 or w % 32:
            raise ValueError(f"img_size {self.img_size} must be multiples of 32")
        if len(self.anchors) != len(self.strides) or any(len(a) != 3 for a in self.anchors):
            raise ValueError("anchors must be 3 levels x 3 (w, h) pairs matching strides")
        if self.dw_impl not in DW_IMPLS:
            raise ValueError(f"dw_impl must be one of {DW_IMPLS}, got {self.dw_impl!r}")
        # Normalise anchors to nested tuples of floats (hashable; lists from JSON are fine).
        object.__setattr__(
            self,
            "anchors",
            tuple(tuple((float(a[0]), float(a[1])) for a in lvl) for lvl in self.anchors),
        )
        object.__setattr__(self, "img_size", (int(h), int(w)))
        object.__setattr__(self, "strides", tuple(int(s) for s in self.strides))
        object.__setattr__(self, "balance", tuple(float(b) for b in self.balance))
        if self.neck_widths is not None:
            object.__setattr__(self, "neck_widths", tuple(int(c) for c in self.neck_widths))

    # ----------------------------------------------------------------------------------
    @property
    def num_levels(self) -> int:
        return len(self.strides)

    @property
    def num_anchors(self) -> int:
        return len(self.anchors[0])

    @property
    def num_outputs(self) -> int:
        """Channels per anchor: x, y, w, h, objectness and one logit per class."""
        return 5 + self.num_classes

    @property
    def widths(self) -> tuple[int, int, int]:
        return self.neck_widths if self.neck_widths is not None else NECK_WIDTHS[self.model]

    @property
    def depth(self) -> int:
        return self.neck_depth if self.neck_depth is not None else NECK_DEPTH[self.model]

    def grid_sizes(self) -> tuple[tuple[int, int], ...]:
        """``(H/s, W/s)`` of each output level."""
        h, w = self.img_size
        return tuple((h // s, w // s) for s in self.strides)

    def scaled_gains(self) -> tuple[float, float, float]:
        """(box, obj, cls) gains after v7.0 ``train.py``'s scaling with ``imgsz = max(H, W)``."""
        nl = self.num_levels
        imgsz = max(self.img_size)
        box = self.box_gain * 3.0 / nl
        cls = self.cls_gain * self.num_classes / 80.0 * 3.0 / nl
        obj = self.obj_gain * (imgsz / 640.0) ** 2 * 3.0 / nl
        return box, obj, cls

    def replace(self, **changes) -> DetectorConfig:
        return replace(self, **changes)


# ----------------------------------------------------------------------------- prediction


@dataclass(frozen=True)
class PredictConfig:
    """Post-processing of the head outputs (see :func:`uavcal_jax.detect.nms.postprocess`).

    The defaults are YOLOv5 ``detect.py``'s, for use (:data:`SERVE_PREDICT`);
    :data:`EVAL_PREDICT` is ``val.py``'s, for mAP.

    Attributes:
        conf_thresh: a candidate needs objectness and score (objectness x class probability)
            above this.
        iou_thresh: NMS suppresses a box overlapping a kept one of its class by IoU > this.
        max_det: detections kept per image (the fixed output size).
        multi_label: every (box, class) pair above ``conf_thresh`` is a candidate, instead of
            each box's best class only.
        agnostic: NMS across classes.
        pre_nms_topk: the candidates entering NMS, best scores first.
    """

    conf_thresh: float = 0.25
    iou_thresh: float = 0.45
    max_det: int = 300
    multi_label: bool = False
    agnostic: bool = False
    pre_nms_topk: int = 1000

    def replace(self, **changes) -> PredictConfig:
        return replace(self, **changes)


#: For use: YOLOv5 ``detect.py`` (conf 0.25, IoU 0.45, 300 detections, best class per box).
SERVE_PREDICT = PredictConfig()
#: For mAP: YOLOv5 ``val.py`` (conf 0.001, IoU 0.6, multi-label).
EVAL_PREDICT = PredictConfig(conf_thresh=0.001, iou_thresh=0.6, multi_label=True)


# ----------------------------------------------------------------------------- training

#: ``TrainConfig.optimizer``: the paper's RMSprop or YOLOv5's SGD.
OPTIMIZERS = ("rmsprop", "sgd")
#: ``TrainConfig.lr_schedule``: the per-epoch learning-rate decay.
SCHEDULES = ("constant", "linear", "cosine")
#: ``TrainConfig.select_metric``: the best-model criterion.
SELECT_METRICS = ("map50_95", "map50", "fitness")


@dataclass(frozen=True)
class TrainConfig:
    """Everything about a training run except the model (:class:`DetectorConfig`).

    The defaults are the paper's (RMSprop, lr 0.01, momentum 0.9, weight decay 1e-5,
    batch 8); :meth:`yolov5` gives YOLOv5's SGD recipe. ``predict`` is how validation
    predicts (:data:`EVAL_PREDICT`); ``map_max_dets`` the detections per image the mAP counts
    (COCO's 100).
    """

    epochs: int = 100
    batch_size: int = 8
    optimizer: str = "rmsprop"
    lr: float = 0.01
    momentum: float = 0.9
    weight_decay: float = 1e-5
    rmsprop_decay: float = 0.9
    rmsprop_eps: float = 1e-3
    nesterov: bool = True
    lr_schedule: str = "cosine"
    lrf: float = 0.01
    warmup_epochs: float = 3.0
    warmup_min_steps: int = 100
    warmup_bias_lr: float = 0.1
    warmup_momentum: float = 0.8
    grad_clip: float = 10.0
    ema: bool = True
    ema_decay: float = 0.9999
    ema_tau: float = 2000.0
    seed: int = 0
    augment: AugmentConfig | None = field(default_factory=AugmentConfig)
    val_fraction: float = 0.2
    split_seed: int = 0
    eval_every: int = 1
    predict: PredictConfig = EVAL_PREDICT
    map_max_dets: int = COCO_MAX_DETS
    select_metric: str = "map50_95"
    workers: int = 2
    cache: bool = True
    autoanchor: bool = True
    #: a trained run folder (or the shipped ``uavcal_jax/detect/weights/default``) whose best
    #: weights start the training instead of random ones: fine-tuning. Its model, anchors and
    #: class names are kept (the data set must name the same classes); autoanchor is skipped.
    init_from: str | None = None

    def __post_init__(self):
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, not {self.optimizer!r}")
        if self.lr_schedule not in SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {SCHEDULES}")
        if self.select_metric not in SELECT_METRICS:
            raise ValueError(f"select_metric must be one of {SELECT_METRICS}")
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError("epochs and batch_size must be >= 1")
        if isinstance(self.augment, dict):  # read back from config.json
            object.__setattr__(self, "augment", AugmentConfig(**self.augment))
        if isinstance(self.predict, dict):
            object.__setattr__(self, "predict", PredictConfig(**self.predict))

    @classmethod
    def paper(cls, **changes) -> TrainConfig:
        """RPEOD section 6.2: RMSprop, lr 0.01, momentum 0.9, weight decay 1e-5, batch 8."""
        return cls(**changes)

    @classmethod
    def yolov5(cls, **changes) -> TrainConfig:
        """YOLOv5 v7.0 ``hyp.scratch-low``: Nesterov SGD, lr0 0.01, momentum 0.937, weight
        decay 5e-4, 3 warmup epochs, linear decay to lrf 0.01."""
        base = dict(optimizer="sgd", lr=0.01, momentum=0.937, weight_decay=5e-4,
                    lr_schedule="linear", lrf=0.01)
        return cls(**{**base, **changes})



# ----------------------------------------------------------------------------- the root


@dataclass(frozen=True)
class DetectConfig:
    """The detector task's root configuration: the model and its training run.

    A run folder's ``config.json`` is this tree (plus the data set's description under
    ``data``); ``uavcal detect train --set`` takes its dotted keys (``detector.model``,
    ``train.lr``, ``train.augment.mosaic``, ``train.predict.conf_thresh``...).
    """

    detector: DetectorConfig = field(default_factory=DetectorConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
