"""Sliced inference: small objects in large images (SAHI, Akyon et al. 2022, its
``get_sliced_prediction``).

A letterboxed network input shrinks a large photo: at the shipped detector's 256x384 input a
4000x3000 aerial photo is scaled by 0.085, and a 40 px car becomes 3 px, below what the head
resolves. Sliced inference runs the network on overlapping windows of the image at its own
resolution instead, each window the size of the network input, plus (SAHI's
``perform_standard_pred``) once on the whole letterboxed image for the objects larger than a
window; the windows' boxes are shifted back into the image and all of them merged by a
class-wise greedy NMS.

Differences from SAHI, and why:

- The windows are spread evenly between the image's borders (their count is SAHI's: the
  fewest whose overlap is at least ``overlap`` of a window), where SAHI keeps a fixed stride
  and moves the last window back to the border: the overlaps are then equal and no window
  nearly repeats another.
- Merging is greedy NMS on SAHI's default match metric, the intersection over the smaller box
  (IOS) above 0.5, not SAHI's default greedy non-maximum *merging*: a box cut by a window's
  edge lies inside the whole box another window (or the full image) finds, so IOS removes it
  where IoU (about the cut fraction) may not, and the box kept is a box the network predicted,
  not a union of them.
- Every window and the full image go through the predict function in batches of a fixed
  ``batch_size`` (a short batch is padded): one compiled shape for every image size.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from uavcal_jax.detect.config import SERVE_PREDICT
from uavcal_jax.detect.predict import ImageDetections, detect_images

__all__ = ["AUTO_MIN_SCALE", "MATCH_METRICS", "TILE_MODES", "TileConfig", "detect",
           "detect_tiled", "merge_detections", "needs_slicing", "tile_origins", "tile_windows"]

#: ``--tile auto``'s threshold: an image is sliced when its width or height exceeds the network
#: input's by more than this factor. Below it a letterboxed image keeps at least 1/1.5 of its
#: resolution, where the network still resolves what the windows would (the real aerial set's
#: 1764x430 photos are 2.8 times a 640 input: whole, their cars shrink to 14x7 px and mAP@0.5
#: falls from 0.65 sliced to 0.11).
AUTO_MIN_SCALE = 1.5
#: The ``--tile`` modes: ``auto`` (slice images larger than :data:`AUTO_MIN_SCALE` times the
#: input), ``on`` (slice every image larger than the input, SAHI's rule), ``off``.
TILE_MODES = ("auto", "on", "off")

#: How two boxes of a class are matched when merging: intersection over the smaller box's area
#: (SAHI's default) or over the union.
MATCH_METRICS = ("ios", "iou")


@dataclass(frozen=True)
class TileConfig:
    """Sliced inference's settings (SAHI's defaults).

    Attributes:
        overlap: the least overlap of two neighbouring windows, a fraction of the window's
            side (SAHI's ``overlap_height_ratio`` and ``overlap_width_ratio``), in [0, 1).
        full_image: predict on the whole letterboxed image as well (SAHI's
            ``perform_standard_pred``): objects larger than a window are found whole.
        match_metric: one of :data:`MATCH_METRICS` (SAHI's ``postprocess_match_metric``).
        match_thresh: a box matching a better-scored box of its class by more than this is
            dropped (SAHI's ``postprocess_match_threshold``).
        batch_size: windows per predict call (a short batch is padded).
        min_scale: an image is sliced only when its width or height exceeds the window's by
            more than this factor; one that does not is letterboxed whole (1: every image
            larger than a window is sliced; :data:`AUTO_MIN_SCALE` for ``--tile auto``).
    """

    overlap: float = 0.2
    full_image: bool = True
    match_metric: str = "ios"
    match_thresh: float = 0.5
    batch_size: int = 8
    min_scale: float = 1.0

    @classmethod
    def of_mode(cls, mode: str, **changes) -> TileConfig | None:
        """The settings of a ``--tile`` mode (:data:`TILE_MODES`): ``None`` for ``off``."""
        if mode not in TILE_MODES:
            raise ValueError(f"tile mode must be one of {', '.join(TILE_MODES)}, got {mode!r}")
        if mode == "off":
            return None
        return cls(**{"min_scale": AUTO_MIN_SCALE if mode == "auto" else 1.0, **changes})

    def __post_init__(self):
        if not 0.0 <= self.overlap < 1.0:
            raise ValueError(f"tile overlap must be in [0, 1), got {self.overlap}")
        if self.match_metric not in MATCH_METRICS:
            raise ValueError(f"tile match_metric must be one of {', '.join(MATCH_METRICS)}, "
                             f"got {self.match_metric!r}")
        if self.batch_size < 1:
            raise ValueError(f"tile batch_size must be >= 1, got {self.batch_size}")
        if self.min_scale < 1.0:
            raise ValueError(f"tile min_scale must be >= 1, got {self.min_scale}")

    def replace(self, **changes) -> TileConfig:
        return replace(self, **changes)


def tile_origins(length: int, size: int, overlap: float) -> np.ndarray:
    """The first pixels of the windows of ``size`` pixels along a side of ``length`` pixels:
    ``(n,)`` int, the first 0, the last ``length - size``, evenly spread, ``n`` the fewest for
    which neighbours overlap by at least ``int(overlap * size)`` pixels (SAHI's count). One
    window at 0 when the side fits into one."""
    if length <= size:
        return np.zeros(1, np.int64)
    step = size - int(overlap * size)
    n = math.ceil((length - size) / step) + 1
    return np.round(np.linspace(0, length - size, n)).astype(np.int64)


def tile_windows(image_size: tuple[int, int], tile_size: tuple[int, int], overlap: float
                 ) -> np.ndarray:
    """The windows over an image: ``(n, 4)`` int ``x0, y0, x1, y1`` pixels (``x1, y1``
    exclusive), row by row.

    Args:
        image_size: the image's ``(height, width)``.
        tile_size: a window's ``(height, width)`` (the network input); a side of the image
            shorter than the window's gives windows of the image's side.
        overlap: as :attr:`TileConfig.overlap`.
    """
    (h, w), (th, tw) = image_size, tile_size
    th, tw = min(th, h), min(tw, w)
    return np.asarray([(x, y, x + tw, y + th) for y in tile_origins(h, th, overlap)
                       for x in tile_origins(w, tw, overlap)], np.int64).reshape(-1, 4)


def merge_detections(det: ImageDetections, metric: str = TileConfig.match_metric,
                     thresh: float = TileConfig.match_thresh,
                     max_det: int = SERVE_PREDICT.max_det) -> ImageDetections:
    """Class-wise greedy NMS: best score first (earlier rows first among equal scores), a box
    matching a kept box of its class by more than ``thresh`` (``metric``, one of
    :data:`MATCH_METRICS`) is dropped; at most ``max_det`` kept. Boxes ``x0, y0, x1, y1``."""
    boxes = np.asarray(det.boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(det.scores, np.float64)
    classes = np.asarray(det.classes, np.int64)
    order = np.argsort(-scores, kind="stable")
    boxes, scores, classes = boxes[order], scores[order], classes[order]
    area = np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1],
                                                                  0, None)
    dropped = np.zeros(len(scores), bool)
    keep = []
    # one row of matches per kept box (not the whole matrix: a large photo's hundreds of
    # windows give tens of thousands of candidates at an evaluation's low threshold)
    for i in range(len(scores)):
        if dropped[i]:
            continue
        keep.append(i)
        if len(keep) == max_det:
            break
        lo = np.maximum(boxes[i, :2], boxes[:, :2])
        hi = np.minimum(boxes[i, 2:], boxes[:, 2:])
        inter = np.prod(np.clip(hi - lo, 0, None), axis=-1)
        denom = np.minimum(area[i], area) if metric == "ios" else area[i] + area - inter
        dropped |= (inter > thresh * np.maximum(denom, 1e-12)) & (classes == classes[i])
    keep = np.asarray(keep, np.int64)
    return ImageDetections(boxes[keep], scores[keep], classes[keep])


def needs_slicing(image_size: tuple[int, int], img_size: tuple[int, int],
                  tile: TileConfig | None) -> bool:
    """Whether ``tile`` slices an image of ``image_size = (height, width)`` for a network
    input ``img_size = (H, W)``: it exceeds the input's height or width by more than
    ``tile.min_scale`` (never without ``tile``)."""
    if tile is None:
        return False
    (h, w), (H, W) = image_size, img_size
    return (h > H or w > W) and max(h / H, w / W) > tile.min_scale


def detect_tiled(predict_fn: Callable, images_rgb: Sequence[np.ndarray],
                 img_size: tuple[int, int], tile: TileConfig = TileConfig(),
                 max_det: int = SERVE_PREDICT.max_det) -> list[ImageDetections]:
    """Sliced-inference detections of decoded images, each in its own pixels.

    Args:
        predict_fn: ``predict_fn(images (B, H, W, 3)) -> Detections``, as
            :func:`~uavcal_jax.detect.predict.detect_letterboxed` takes; ``B`` is always
            ``tile.batch_size``.
        images_rgb: uint8 (h, w, 3) RGB images of any sizes.
        img_size: the network input ``(H, W)``, also the windows' size.
        tile: the windows' overlap, the full-image pass and the merge.
        max_det: detections kept per image after merging.

    An image that fits into one window, or exceeds it by no more than ``tile.min_scale``,
    gets the full-image pass only (as :func:`~uavcal_jax.detect.predict.detect_images`).
    """
    H, W = img_size
    sliced = [needs_slicing(image.shape[:2], img_size, tile) for image in images_rgb]
    # the images seen whole go through in batches of their own
    whole = iter(detect_images(predict_fn, [im for im, s in zip(images_rgb, sliced,
                                                                  strict=True) if not s],
                               img_size, tile.batch_size))
    out = []
    for image, slice_it in zip(images_rgb, sliced, strict=True):
        if not slice_it:
            out.append(next(whole))
            continue
        h, w = image.shape[:2]
        windows = tile_windows((h, w), (H, W), tile.overlap)
        # the windows first: among equal scores a window's box (full resolution) is kept
        crops = [image[y0:y1, x0:x1] for x0, y0, x1, y1 in windows]
        shifts = [(float(x0), float(y0)) for x0, y0, _, _ in windows]
        if tile.full_image:
            crops.append(image)
            shifts.append((0.0, 0.0))
        found = detect_images(predict_fn, crops, img_size, tile.batch_size)
        shifted = [d.boxes + np.asarray([dx, dy, dx, dy]) for d, (dx, dy)
                   in zip(found, shifts, strict=True)]
        out.append(merge_detections(
            ImageDetections(np.concatenate(shifted).reshape(-1, 4),
                            np.concatenate([d.scores for d in found]),
                            np.concatenate([d.classes for d in found])),
            tile.match_metric, tile.match_thresh, max_det))
    return out


def detect(predict_fn: Callable, images_rgb: Sequence[np.ndarray], img_size: tuple[int, int],
           batch_size: int = 1, tile: TileConfig | None = None,
           max_det: int = SERVE_PREDICT.max_det) -> list[ImageDetections]:
    """Detections of decoded images, each in its own pixels: letterboxed whole
    (:func:`~uavcal_jax.detect.predict.detect_images`, ``batch_size`` images per call) when
    ``tile`` is ``None``, else sliced (:func:`detect_tiled`)."""
    if tile is None:
        return detect_images(predict_fn, images_rgb, img_size, batch_size)
    return detect_tiled(predict_fn, images_rgb, img_size, tile, max_det)
