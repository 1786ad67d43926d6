"""The detectors ``uavcal run`` can use, behind one small interface (:class:`Detector`).

A detector is called on a batch of left-camera frames, ``detector(images, t_ns)``: ``images``
are uint8 RGB (H, W, 3) (``None`` each when it says ``needs_images = False``), ``t_ns`` their
timestamps; it returns one :class:`~uavcal_jax.detect.predict.ImageDetections` per frame
(boxes in the image's own pixels, pixel-edge coordinates ``x1, y1, x2, y2``; scores; class
ids into ``class_names``).

- :class:`NetworkDetector`: a trained detector (a ``uavcal detect train`` run folder, its best
  EMA weights); :func:`load_network_detector` reads one, by default the weights shipped in the
  package (:func:`uavcal_jax.detect.default_weights.default_detector_run`).
- :class:`LabelDetector`: the recording's own target labels (the simulator's boxes of each
  target's visible pixels) as detections: a perfect detector, for tests and for measuring
  the rest of the pipeline apart from the network.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from uavcal_jax.data.targets import TargetLabels
from uavcal_jax.detect.config import SERVE_PREDICT
from uavcal_jax.detect.default_weights import default_detector_run
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.detect.tile import TileConfig, detect
from uavcal_jax.errors import DataError

__all__ = ["Detector", "LabelDetector", "NetworkDetector", "load_network_detector"]


class Detector(Protocol):
    """What the run calls to detect targets (see the module docstring)."""

    class_names: tuple[str, ...]
    needs_images: bool

    def __call__(self, images: Sequence[np.ndarray | None], t_ns: Sequence[int]
                 ) -> list[ImageDetections]: ...


def _empty() -> ImageDetections:
    return ImageDetections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64))


@dataclasses.dataclass(frozen=True, eq=False)
class NetworkDetector:
    """A trained detector: ``predict_fn(images) -> Detections`` bound to its weights, run on
    letterboxed images of size ``img_size`` (H, W) (:func:`uavcal_jax.detect.predict.
    detect_images`), or on windows of them when ``tile`` is given
    (:func:`uavcal_jax.detect.tile.detect_tiled`, at most ``max_det`` boxes a frame)."""

    predict_fn: Callable
    img_size: tuple[int, int]
    class_names: tuple[str, ...]
    source: Path
    needs_images: bool = True
    tile: TileConfig | None = None
    max_det: int = SERVE_PREDICT.max_det

    def __call__(self, images, t_ns) -> list[ImageDetections]:
        return detect(self.predict_fn, list(images), self.img_size, batch_size=len(images),
                      tile=self.tile, max_det=self.max_det)


def load_network_detector(run: str | Path | None, score_threshold: float,
                          tile: TileConfig | None = None) -> NetworkDetector:
    """The detector of a ``uavcal detect train`` run folder ``run`` (its best weights), or
    the shipped one (:func:`uavcal_jax.detect.default_weights.default_detector_run`) when
    ``run`` is ``None``; detections below ``score_threshold`` are dropped (the serving NMS
    settings otherwise; ``uavcal run`` passes
    :meth:`~uavcal_jax.pipeline.run_config.DetectStageConfig.detector_threshold`); ``tile``:
    sliced inference (``DetectStageConfig.tile_config``), ``None`` for none.

    Raises:
        DataError: the folder is missing or is not a training run with a best checkpoint (the
            message names it and, for the shipped weights, says to give ``--detector RUN``).
    """
    # the shipped folder's check raises a DataError naming it when it is missing
    path = default_detector_run() if run is None else Path(run)
    if not (path / "config.json").is_file() or not (path / "checkpoints" / "best").is_dir():
        what = "no such run folder" if not path.exists() else (
            "not a detector training run (needs config.json and checkpoints/best)")
        raise DataError(what, path)
    from uavcal_jax.detect.predict import make_predict_fn
    from uavcal_jax.detect.run import load_run

    absl = logging.getLogger("absl")
    level = absl.level
    absl.setLevel(logging.ERROR)  # orbax's notes on a read-only checkpoint are no news
    try:
        loaded = load_run(path)
    finally:
        absl.setLevel(level)
    predict_cfg = SERVE_PREDICT.replace(conf_thresh=float(score_threshold))
    fn = functools.partial(make_predict_fn(loaded.det_cfg, predict_cfg), loaded.variables)
    names = tuple(loaded.data.get("class_names") or ())
    if not names:
        raise DataError("the run's config.json names no classes", path / "config.json")
    return NetworkDetector(fn, tuple(loaded.det_cfg.img_size), names, path, tile=tile,
                           max_det=predict_cfg.max_det)


class LabelDetector:
    """The recording's target labels (camera ``camera``) as detections, score 1.

    A label counts from ``min_visible_pixels`` visible pixels on (a sliver of an occluded
    target is no detection a network would make). Frames are looked up by timestamp; the
    images are not needed.
    """

    needs_images = False

    def __init__(self, labels: TargetLabels, camera: str = "cam0",
                 min_visible_pixels: int = 40):
        self.class_names = tuple(labels.class_names)
        keep = (labels.camera == camera) & (labels.visible_pixels >= min_visible_pixels)
        self._rows: dict[int, np.ndarray] = {}
        for row in np.flatnonzero(keep):
            self._rows.setdefault(int(labels.t_ns[row]), []).append(row)
        self._labels = labels

    def __call__(self, images, t_ns) -> list[ImageDetections]:
        out = []
        for t in t_ns:
            rows = np.asarray(self._rows.get(int(t), []), np.int64)
            if rows.size == 0:
                out.append(_empty())
                continue
            out.append(ImageDetections(self._labels.box[rows].astype(np.float64),
                                       np.ones(rows.size), self._labels.class_id[rows]))
        return out
