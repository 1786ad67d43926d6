"""Detector configuration: one frozen dataclass whose defaults are YOLOv5 v7.0's settings.

The loss gains are YOLOv5's ``hyp.scratch-low.yaml`` values (box 0.05, obj 1.0, cls 0.5);
:meth:`DetectorConfig.scaled_gains` applies the scaling that v7.0's ``train.py`` does before
training (``box *= 3/nl``, ``cls *= nc/80 * 3/nl``, ``obj *= (imgsz/640)**2 * 3/nl``).
Anchors are in pixels of the network input, three (w, h) pairs per level, YOLOv5's defaults
for strides 8, 16 and 32 (``models/yolov5n.yaml``); k-means anchors fitted on training labels
can be passed instead (``anchors=...``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

#: YOLOv5's default anchors (pixels), P3/8, P4/16, P5/32.
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
        bn_momentum, bn_eps: batch-norm running-average decay (Flax convention; YOLOv5's
            torch momentum 0.03 is 0.97 here) and epsilon (YOLOv5: 1e-3).
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
    bn_momentum: float = 0.97
    bn_eps: float = 1e-3
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
        if self.dw_impl not in ("shift", "grouped"):
            raise ValueError(f"dw_impl must be 'shift' or 'grouped', got {self.dw_impl!r}")
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

    def to_dict(self) -> dict:
        """A JSON-ready dict (tuples become lists) that :meth:`from_dict` reads back."""
        out = {}
        for name in self.__dataclass_fields__:
            out[name] = _listify(getattr(self, name))
        return out

    @classmethod
    def from_dict(cls, d: dict) -> DetectorConfig:
        kw = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        for key in ("img_size", "strides", "balance", "neck_widths"):
            if kw.get(key) is not None:
                kw[key] = tuple(kw[key])
        return cls(**kw)


def _listify(x):
    if isinstance(x, tuple | list):
        return [_listify(v) for v in x]
    return x
