"""Inference: one pure jitted function (images -> network -> decode -> NMS), and the one host
path from images to boxes in their own pixels.

:func:`make_predict_fn` builds the jitted ``fn(variables, images) -> Detections`` of a
configuration and a :class:`~uavcal_jax.detect.config.PredictConfig`.
:func:`detect_letterboxed` runs any such function (bound to its weights, or a deserialised
export) on a letterboxed batch and maps the kept boxes back into each original image;
:func:`detect_images` letterboxes decoded images first. Training's validation, ``uavcal detect
eval`` and ``predict`` and :class:`~uavcal_jax.detect.export.ExportedDetector` all go through
:func:`detect_letterboxed`.

The model is imported only when a predict function is built, so serving an exported detector
needs JAX, NumPy and OpenCV only.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import jax
import numpy as np

from uavcal_jax.detect.augment import PAD_VALUE, letterbox, unletterbox_boxes
from uavcal_jax.detect.config import SERVE_PREDICT, DetectorConfig, PredictConfig
from uavcal_jax.detect.nms import Detections


def predict(variables, images, config: DetectorConfig,
            predict_cfg: PredictConfig = SERVE_PREDICT) -> Detections:
    """Un-jitted predict: ``images (B, H, W, 3)`` float32 in [0, 1] -> :class:`Detections`
    ``(B, max_det, ...)`` in pixels of the network input."""
    from uavcal_jax.detect.model import build_detector
    from uavcal_jax.detect.nms import postprocess

    outputs = build_detector(config).apply(variables, images, train=False)
    return postprocess(outputs, config, predict_cfg)


@functools.lru_cache(maxsize=16)
def make_predict_fn(config: DetectorConfig, predict_cfg: PredictConfig = SERVE_PREDICT
                    ) -> Callable:
    """A jitted ``fn(variables, images) -> Detections`` (variables: params + batch_stats),
    cached per configuration so that repeated evaluations compile once."""

    def fn(variables, images):
        return predict({"params": variables["params"], "batch_stats": variables["batch_stats"]},
                       images, config, predict_cfg)

    return jax.jit(fn)


class ImageDetections(NamedTuple):
    """The detections of one image, in its own pixels.

    Attributes:
        boxes: (m, 4) float64 ``x_min, y_min, x_max, y_max``, clipped to the image.
        scores: (m,) float64, best first.
        classes: (m,) int64 class ids.
    """

    boxes: np.ndarray
    scores: np.ndarray
    classes: np.ndarray

    def above(self, threshold: float) -> ImageDetections:
        """The detections scoring at least ``threshold``."""
        keep = np.asarray(self.scores) >= threshold
        return ImageDetections(np.asarray(self.boxes, np.float64)[keep].reshape(-1, 4),
                               np.asarray(self.scores, np.float64)[keep],
                               np.asarray(self.classes, np.int64)[keep])


def detect_letterboxed(predict_fn: Callable, images, ratios: Sequence[float],
                       pads: Sequence[tuple[float, float]], sizes: Sequence[tuple[int, int]]
                       ) -> list[ImageDetections]:
    """Run ``predict_fn`` on a letterboxed batch and map each image's boxes back.

    Args:
        predict_fn: ``predict_fn(images) -> Detections`` (or a mapping with the same
            fields), e.g. :func:`make_predict_fn`'s function bound to its variables.
        images: (B, H, W, 3) float32 RGB in [0, 1], letterboxed.
        ratios, pads: per image of the first ``n <= B`` (the rest is padding): a point ``p`` of
            the original image lands at ``p * ratio + pad`` (``pad = (left, top)`` pixels).
        sizes: ``(width, height)`` of each original image.
    """
    det = predict_fn(images)
    if isinstance(det, Mapping):
        det = Detections(**{k: det[k] for k in Detections._fields})
    boxes, scores = np.asarray(det.boxes), np.asarray(det.scores)
    classes, valid = np.asarray(det.classes), np.asarray(det.valid).astype(bool)
    out = []
    for j, (ratio, pad, size) in enumerate(zip(ratios, pads, sizes, strict=True)):
        keep = valid[j]
        out.append(ImageDetections(
            unletterbox_boxes(boxes[j][keep], float(ratio), (float(pad[0]), float(pad[1])),
                              (int(size[0]), int(size[1]))),
            scores[j][keep].astype(np.float64), classes[j][keep].astype(np.int64)))
    return out


def detect_images(predict_fn: Callable, images_rgb: Sequence[np.ndarray],
                  img_size: tuple[int, int], batch_size: int = 1) -> list[ImageDetections]:
    """Detections of decoded images, each in its own pixels.

    Args:
        predict_fn: as :func:`detect_letterboxed`.
        images_rgb: uint8 (h, w, 3) RGB images of any sizes.
        img_size: the network input ``(H, W)``; each image is letterboxed into it.
        batch_size: images per call; a short last batch is padded (one compiled shape).
    """
    H, W = img_size
    out: list[ImageDetections] = []
    for start in range(0, len(images_rgb), batch_size):
        chunk = images_rgb[start:start + batch_size]
        batch = np.full((batch_size, H, W, 3), PAD_VALUE / 255, np.float32)
        ratios, pads, sizes = [], [], []
        for j, image in enumerate(chunk):
            boxed, ratio, pad = letterbox(image, (H, W))
            batch[j] = boxed.astype(np.float32) / 255.0
            ratios.append(ratio)
            pads.append(pad)
            sizes.append((image.shape[1], image.shape[0]))
        out += detect_letterboxed(predict_fn, batch, ratios, pads, sizes)
    return out


def predict_dataset(predict_fn: Callable, loader, progress: Callable | None = None
                    ) -> list[ImageDetections]:
    """Detections of every record of an un-augmented
    :class:`~uavcal_jax.detect.loader.DetectionLoader`, by record, in original image pixels.

    ``predict_fn(images) -> Detections``; ``progress(iterable, total=...)`` wraps the batches.
    """
    out: list = [None] * len(loader.records)
    batches = loader.epoch(0)
    if progress is not None:
        batches = progress(batches, total=len(loader))
    for batch in batches:
        rows = [j for j, idx in enumerate(batch.indices) if idx >= 0]
        records = [loader.records[batch.indices[j]] for j in rows]
        found = detect_letterboxed(predict_fn, batch.images, batch.ratios[rows],
                                   batch.pads[rows], [(r.width, r.height) for r in records])
        for j, dets in zip(rows, found, strict=True):
            out[batch.indices[j]] = dets
    return out
