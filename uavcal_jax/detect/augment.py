"""Image geometry and augmentation for the detector, in NumPy/OpenCV (host side).

Images are ``uint8`` (H, W, 3) RGB; boxes are (n, 4) ``x_min, y_min, x_max, y_max`` pixels.
The pieces follow YOLOv5 v7.0 (``utils/augmentations.py``, ``utils/dataloaders.py``):
letterbox, a random affine restricted to scale and translation (rotation/shear available,
off by default), horizontal flip, HSV jitter and the 4-image mosaic. :func:`random_crop` adds
multi-scale crops at the stored resolution (small objects in large photos keep their pixels:
YOLOv5's ``--multi-scale`` without recompiling for every input size). Every random function
takes a ``numpy.random.Generator`` so a sample is a pure function of its seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

PAD_VALUE = 114


@dataclass(frozen=True)
class AugmentConfig:
    """Training augmentation (defaults: YOLOv5 ``hyp.scratch-low.yaml``).

    Attributes:
        scale: random zoom factor range ``1 +- scale``.
        translate: random shift, fraction of the output size.
        degrees, shear: rotation and shear in degrees (0: off, as the paper's set-up).
        fliplr: probability of a horizontal flip.
        hsv_h, hsv_s, hsv_v: HSV gains.
        mosaic: probability of a 4-image mosaic (0: off; YOLOv5 uses 1.0).
        min_box_px: boxes narrower or lower than this after augmentation are dropped.
        min_area_ratio: boxes that keep less than this fraction of their (scaled) area are
            dropped.
        crop_scale: ``(lo, hi)`` turns on :func:`random_crop`: each sample is a
            ``crop_size`` window of the image at its stored resolution zoomed by a
            log-uniform factor in ``[lo, hi]`` (rotated by up to ``degrees``), instead of the
            letterboxed whole image; ``None``: off.
        crop_size: ``(H, W)`` of the training crops (multiples of 32; the network is fully
            convolutional, so it still predicts at ``DetectorConfig.img_size``).
        crop_on_object: probability that a crop is centred on a random labelled object
            (else anywhere): dense-enough batches from large, sparse photos.
        rot90: probability that a crop is turned by a random quarter turn (a nadir view has
            no up; unlike a large ``degrees``, it keeps axis-aligned boxes tight).
        gray: probability of turning a sample grey (one luminance copied to the three
            channels): a set mixing colour photos with grey cameras' frames (EuRoC's).
    """

    scale: float = 0.5
    translate: float = 0.1
    degrees: float = 0.0
    shear: float = 0.0
    fliplr: float = 0.5
    hsv_h: float = 0.015
    hsv_s: float = 0.7
    hsv_v: float = 0.4
    mosaic: float = 0.0
    min_box_px: float = 2.0
    min_area_ratio: float = 0.1
    crop_scale: tuple[float, float] | None = None
    crop_size: tuple[int, int] = (320, 320)
    crop_on_object: float = 0.5
    rot90: float = 0.0
    gray: float = 0.0

    def __post_init__(self):
        # read back from JSON as lists
        if self.crop_scale is not None:
            object.__setattr__(self, "crop_scale", tuple(float(v) for v in self.crop_scale))
        object.__setattr__(self, "crop_size", tuple(int(v) for v in self.crop_size))


def resize_long_side(image: np.ndarray, boxes: np.ndarray, long_side: int,
                     interpolation: int | None = None):
    """Resize so that the longer side is ``long_side`` (YOLOv5 ``load_image``).

    Returns ``(image, boxes, ratio)``.
    """
    h, w = image.shape[:2]
    r = long_side / max(h, w)
    if r == 1.0:
        return image, boxes.astype(np.float32), 1.0
    interp = interpolation if interpolation is not None else (
        cv2.INTER_LINEAR if r > 1 else cv2.INTER_AREA)
    image = cv2.resize(image, (max(1, round(w * r)), max(1, round(h * r))),
                       interpolation=interp)
    return image, (boxes * r).astype(np.float32), r


def letterbox(image: np.ndarray, shape: tuple[int, int], *, scaleup: bool = True,
              color: int = PAD_VALUE, interpolation: int = cv2.INTER_LINEAR):
    """Resize keeping the aspect ratio and pad to ``shape = (H, W)``.

    Returns ``(image, ratio, (pad_left, pad_top))``; a point ``p`` of the input lands at
    ``p * ratio + pad``.
    """
    h, w = image.shape[:2]
    out_h, out_w = shape
    r = min(out_h / h, out_w / w)
    if not scaleup:
        r = min(r, 1.0)
    new_w, new_h = max(1, round(w * r)), max(1, round(h * r))
    if (new_w, new_h) != (w, h):
        image = cv2.resize(image, (new_w, new_h), interpolation=interpolation)
    dw, dh = (out_w - new_w) / 2, (out_h - new_h) / 2
    top, bottom = round(dh - 0.1), round(dh + 0.1)
    left, right = round(dw - 0.1), round(dw + 0.1)
    bottom = out_h - new_h - top
    right = out_w - new_w - left
    image = cv2.copyMakeBorder(image, top, bottom, left, right, cv2.BORDER_CONSTANT,
                               value=(color, color, color))
    # the exact scale per axis after rounding, kept as one number (aspect preserved)
    return image, r, (float(left), float(top))


def scale_boxes(boxes: np.ndarray, ratio: float, pad: tuple[float, float]) -> np.ndarray:
    """Boxes of the input image into the letterboxed image."""
    out = np.asarray(boxes, np.float32).reshape(-1, 4) * ratio
    out[:, [0, 2]] += pad[0]
    out[:, [1, 3]] += pad[1]
    return out


def unletterbox_boxes(boxes: np.ndarray, ratio: float, pad: tuple[float, float],
                      size: tuple[int, int] | None = None) -> np.ndarray:
    """Boxes of the letterboxed image back into the original image (clipped to
    ``size = (width, height)`` when given)."""
    out = np.array(boxes, np.float64).reshape(-1, 4)
    out[:, [0, 2]] -= pad[0]
    out[:, [1, 3]] -= pad[1]
    out /= ratio
    if size is not None:
        out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, size[0])
        out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, size[1])
    return out


def box_candidates(before: np.ndarray, after: np.ndarray, min_px: float = 2.0,
                   min_area_ratio: float = 0.1, max_aspect: float = 100.0) -> np.ndarray:
    """Which boxes survive an augmentation (YOLOv5 ``box_candidates``)."""
    w1, h1 = before[:, 2] - before[:, 0], before[:, 3] - before[:, 1]
    w2, h2 = after[:, 2] - after[:, 0], after[:, 3] - after[:, 1]
    ar = np.maximum(w2 / (h2 + 1e-16), h2 / (w2 + 1e-16))
    return ((w2 > min_px) & (h2 > min_px) & (w2 * h2 / (w1 * h1 + 1e-16) > min_area_ratio)
            & (ar < max_aspect))


def random_affine(image: np.ndarray, boxes: np.ndarray, classes: np.ndarray,
                  rng: np.random.Generator, out_shape: tuple[int, int], *,
                  scale: float = 0.5, translate: float = 0.1, degrees: float = 0.0,
                  shear: float = 0.0, min_box_px: float = 2.0, min_area_ratio: float = 0.1):
    """Random scale/translation (and optional rotation/shear) about the image centre,
    output ``out_shape = (H, W)`` (YOLOv5 ``random_perspective`` without perspective).

    The input's centre goes to the output's centre before the random shift, so a mosaic
    canvas of twice the output size is cropped around its middle.
    """
    h, w = image.shape[:2]
    out_h, out_w = out_shape
    C = np.eye(3)
    C[0, 2], C[1, 2] = -w / 2, -h / 2
    R = np.eye(3)
    a = rng.uniform(-degrees, degrees) if degrees else 0.0
    s = rng.uniform(1 - scale, 1 + scale) if scale else 1.0
    R[:2] = cv2.getRotationMatrix2D(angle=a, center=(0, 0), scale=s)
    S = np.eye(3)
    if shear:
        S[0, 1] = math.tan(rng.uniform(-shear, shear) * math.pi / 180)
        S[1, 0] = math.tan(rng.uniform(-shear, shear) * math.pi / 180)
    T = np.eye(3)
    T[0, 2] = rng.uniform(0.5 - translate, 0.5 + translate) * out_w
    T[1, 2] = rng.uniform(0.5 - translate, 0.5 + translate) * out_h
    M = T @ S @ R @ C
    return _warp(image, boxes, classes, M, s, out_shape, min_box_px, min_area_ratio)


def _warp(image, boxes, classes, M, s, out_shape, min_box_px, min_area_ratio):
    """Apply the 3x3 affine ``M`` (zoom ``s``) to the image and its boxes (the boxes of the
    warped corners, clipped; those :func:`box_candidates` rejects are dropped)."""
    out_h, out_w = out_shape
    image = cv2.warpAffine(image, M[:2], dsize=(out_w, out_h),
                           borderValue=(PAD_VALUE, PAD_VALUE, PAD_VALUE))
    n = len(boxes)
    if n:
        corners = np.ones((n * 4, 3))
        corners[:, :2] = boxes[:, [0, 1, 2, 3, 0, 3, 2, 1]].reshape(n * 4, 2)
        xy = (corners @ M.T)[:, :2].reshape(n, 8)
        x, y = xy[:, [0, 2, 4, 6]], xy[:, [1, 3, 5, 7]]
        new = np.stack([x.min(1), y.min(1), x.max(1), y.max(1)], 1)
        new[:, [0, 2]] = new[:, [0, 2]].clip(0, out_w)
        new[:, [1, 3]] = new[:, [1, 3]].clip(0, out_h)
        keep = box_candidates(boxes * s, new, min_box_px, min_area_ratio)
        boxes, classes = new[keep].astype(np.float32), classes[keep]
    return image, boxes, classes


def random_crop(image: np.ndarray, boxes: np.ndarray, classes: np.ndarray,
                rng: np.random.Generator, out_shape: tuple[int, int], *,
                scale: tuple[float, float], degrees: float = 0.0, rot90: float = 0.0,
                on_object: float = 0.5, min_box_px: float = 2.0, min_area_ratio: float = 0.1):
    """A random ``out_shape = (H, W)`` window of ``image`` zoomed by a log-uniform factor in
    ``scale = (lo, hi)`` and rotated by up to ``degrees`` about its centre (plus, with
    probability ``rot90``, a random quarter turn).

    The window's centre is, with probability ``on_object``, the centre of a random box (moved
    by up to a quarter window), else a uniform point of the image; parts outside the image
    are padded. Boxes are in pixels of ``image`` in, of the window out.
    """
    h, w = image.shape[:2]
    out_h, out_w = out_shape
    s = float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1]))))
    if len(boxes) and rng.random() < on_object:
        b = boxes[rng.integers(len(boxes))]
        centre = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])
        centre += rng.uniform(-0.25, 0.25, 2) * np.array([out_w, out_h]) / s
    else:
        centre = rng.uniform(0, 1, 2) * np.array([w, h])
    a = rng.uniform(-degrees, degrees) if degrees else 0.0
    if rot90 and rng.random() < rot90:
        a += 90.0 * rng.integers(1, 4)
    R = np.eye(3)
    R[:2] = cv2.getRotationMatrix2D(angle=a, center=(0, 0), scale=s)
    C = np.eye(3)
    C[:2, 2] = -centre
    T = np.eye(3)
    T[:2, 2] = out_w / 2, out_h / 2
    # shrinking: blur first so the zoomed-out crop aliases as a real smaller image would
    if s < 0.75:
        image = cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))),
                           interpolation=cv2.INTER_AREA)
        C[:2, 2] *= s
        R[:2, :2] /= s
        boxes = boxes * s
        return _warp(image, boxes, classes, T @ R @ C, 1.0, out_shape, min_box_px,
                     min_area_ratio)
    return _warp(image, boxes, classes, T @ R @ C, s, out_shape, min_box_px, min_area_ratio)


def hflip(image: np.ndarray, boxes: np.ndarray):
    """Mirror left-right."""
    w = image.shape[1]
    out = boxes.copy()
    out[:, 0], out[:, 2] = w - boxes[:, 2], w - boxes[:, 0]
    return np.ascontiguousarray(image[:, ::-1]), out


def augment_hsv(image: np.ndarray, rng: np.random.Generator, hgain: float = 0.015,
                sgain: float = 0.7, vgain: float = 0.4) -> np.ndarray:
    """HSV colour jitter with lookup tables (YOLOv5 ``augment_hsv``); RGB uint8 in and out."""
    if not (hgain or sgain or vgain):
        return image
    r = rng.uniform(-1, 1, 3) * np.array([hgain, sgain, vgain]) + 1
    hue, sat, val = cv2.split(cv2.cvtColor(image, cv2.COLOR_RGB2HSV))
    x = np.arange(0, 256, dtype=r.dtype)
    lut_hue = ((x * r[0]) % 180).astype(np.uint8)
    lut_sat = np.clip(x * r[1], 0, 255).astype(np.uint8)
    lut_val = np.clip(x * r[2], 0, 255).astype(np.uint8)
    hsv = cv2.merge((cv2.LUT(hue, lut_hue), cv2.LUT(sat, lut_sat), cv2.LUT(val, lut_val)))
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def to_gray(image: np.ndarray) -> np.ndarray:
    """RGB uint8 to grey, kept as three equal channels."""
    return cv2.cvtColor(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)


def mosaic4(samples, out_shape: tuple[int, int], rng: np.random.Generator):
    """Tile four ``(image, boxes, classes)`` around a random centre on a ``2H x 2W`` canvas
    (YOLOv5 ``load_mosaic``). Returns the canvas and its boxes; crop it with
    :func:`random_affine` to ``out_shape``."""
    out_h, out_w = out_shape
    yc = int(rng.uniform(out_h / 2, 3 * out_h / 2))
    xc = int(rng.uniform(out_w / 2, 3 * out_w / 2))
    canvas = np.full((2 * out_h, 2 * out_w, 3), PAD_VALUE, dtype=np.uint8)
    all_boxes, all_classes = [], []
    for i, (img, boxes, classes) in enumerate(samples):
        h, w = img.shape[:2]
        if i == 0:  # top left
            x1a, y1a, x2a, y2a = max(xc - w, 0), max(yc - h, 0), xc, yc
            x1b, y1b, x2b, y2b = w - (x2a - x1a), h - (y2a - y1a), w, h
        elif i == 1:  # top right
            x1a, y1a, x2a, y2a = xc, max(yc - h, 0), min(xc + w, 2 * out_w), yc
            x1b, y1b, x2b, y2b = 0, h - (y2a - y1a), min(w, x2a - x1a), h
        elif i == 2:  # bottom left
            x1a, y1a, x2a, y2a = max(xc - w, 0), yc, xc, min(2 * out_h, yc + h)
            x1b, y1b, x2b, y2b = w - (x2a - x1a), 0, w, min(y2a - y1a, h)
        else:  # bottom right
            x1a, y1a, x2a, y2a = xc, yc, min(xc + w, 2 * out_w), min(2 * out_h, yc + h)
            x1b, y1b, x2b, y2b = 0, 0, min(w, x2a - x1a), min(y2a - y1a, h)
        canvas[y1a:y2a, x1a:x2a] = img[y1b:y2b, x1b:x2b]
        dx, dy = x1a - x1b, y1a - y1b
        b = boxes.copy()
        b[:, [0, 2]] += dx
        b[:, [1, 3]] += dy
        all_boxes.append(b)
        all_classes.append(classes)
    boxes = np.concatenate(all_boxes).astype(np.float32) if all_boxes else np.zeros((0, 4))
    classes = np.concatenate(all_classes) if all_classes else np.zeros(0, np.int32)
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, 2 * out_w)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, 2 * out_h)
    keep = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return canvas, boxes[keep], classes[keep]
