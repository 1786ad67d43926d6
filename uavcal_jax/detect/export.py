"""Serve a trained detector without the training code: ``jax.export`` of the predict function.

:func:`export_predict` bakes the (EMA) variables into the jitted ``images -> detections``
function (network, decoding and NMS), serialises it with ``jax.export`` into ``<path>``
(StableHLO, versioned by JAX's compatibility guarantees) and writes ``<path>.json`` beside it
(input size, class names, thresholds). :func:`load_exported` needs only JAX, NumPy and OpenCV:
it deserialises the function and returns an :class:`ExportedDetector` that runs it on
letterboxed batches, or on whole images through :func:`~uavcal_jax.detect.predict.detect_images`
(letterbox in, boxes back in image pixels out).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.detect.augment import PAD_VALUE
from uavcal_jax.detect.config import SERVE_PREDICT, PredictConfig
from uavcal_jax.detect.nms import Detections
from uavcal_jax.detect.predict import detect_images, make_predict_fn
from uavcal_jax.errors import DataError

OUTPUT_NAMES = Detections._fields


def export_predict(variables, det_cfg, path: str | Path, *, class_names=None,
                   predict_cfg: PredictConfig = SERVE_PREDICT, batch_size: int | None = None,
                   platforms=None) -> Path:
    """Export ``images (B, H, W, 3) float32 [0, 1] -> (boxes, scores, classes, valid)``.

    Args:
        variables: ``{"params", "batch_stats"}``, baked into the function as constants.
        det_cfg: the :class:`~uavcal_jax.detect.config.DetectorConfig`.
        path: the output file (``<path>.json`` gets the metadata).
        predict_cfg: the post-processing baked in (default: for use, ``SERVE_PREDICT``).
        batch_size: a fixed batch size, or ``None`` for a symbolic one (any batch).
        platforms: lowering platforms (default: the current backend), e.g.
            ``("cpu", "cuda")``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    predict_fn = make_predict_fn(det_cfg, predict_cfg)
    variables = jax.tree.map(jnp.asarray, {"params": variables["params"],
                                           "batch_stats": variables["batch_stats"]})

    def serve(images):
        det = predict_fn(variables, images)
        return tuple(getattr(det, n) for n in OUTPUT_NAMES)

    h, w = det_cfg.img_size
    kwargs = {} if platforms is None else {"platforms": tuple(platforms)}
    exported = None
    if batch_size is None:
        try:
            (b,) = jax.export.symbolic_shape("b")
            spec = jax.ShapeDtypeStruct((b, h, w, 3), jnp.float32)
            exported = jax.export.export(jax.jit(serve), **kwargs)(spec)
        except Exception:  # noqa: BLE001 - fall back to a fixed batch of one
            exported, batch_size = None, 1
    if exported is None:
        spec = jax.ShapeDtypeStruct((int(batch_size), h, w, 3), jnp.float32)
        exported = jax.export.export(jax.jit(serve), **kwargs)(spec)
    path.write_bytes(exported.serialize())
    meta = {
        "format": "jax.export", "jax_version": jax.__version__,
        "inputs": f"images (B, H, W, 3) float32 RGB in [0, 1], letterboxed (pad "
                  f"{PAD_VALUE}/255)",
        "outputs": list(OUTPUT_NAMES), "img_size": list(det_cfg.img_size),
        "batch_size": batch_size, "model": det_cfg.model, "num_classes": det_cfg.num_classes,
        "class_names": list(class_names) if class_names is not None else None,
        **dataclasses.asdict(predict_cfg),
        "platforms": list(exported.platforms),
    }
    Path(str(path) + ".json").write_text(json.dumps(meta, indent=1))
    return path


@dataclass
class ExportedDetector:
    """A deserialised detector. ``self(images)`` -> dict of numpy arrays by output name."""

    exported: jax.export.Exported
    meta: dict

    @property
    def img_size(self) -> tuple[int, int]:
        return tuple(self.meta["img_size"])

    def __call__(self, images) -> dict:
        images = jnp.asarray(images, jnp.float32)
        fixed = self.meta.get("batch_size")
        n = images.shape[0]
        if fixed is not None and n != fixed:  # run in chunks of the fixed batch size
            parts = [self(np.asarray(images[i:i + fixed])) if images[i:i + fixed].shape[0] ==
                     fixed else self._padded(np.asarray(images[i:i + fixed]), fixed)
                     for i in range(0, n, fixed)]
            return {k: np.concatenate([p[k] for p in parts]) for k in OUTPUT_NAMES}
        out = self.exported.call(images)
        return {k: np.asarray(v) for k, v in zip(OUTPUT_NAMES, out, strict=True)}

    def _padded(self, images: np.ndarray, fixed: int) -> dict:
        pad = np.zeros((fixed - images.shape[0], *images.shape[1:]), np.float32)
        out = self(np.concatenate([images, pad]))
        return {k: v[: images.shape[0]] for k, v in out.items()}

    def detect(self, image_rgb: np.ndarray) -> dict:
        """Detections of one uint8 RGB image, in its own pixels (letterbox handled here):
        ``{"boxes" (m, 4), "scores" (m,), "classes" (m,)}``."""
        return detect_images(self, [image_rgb], self.img_size)[0]._asdict()


def load_exported(path: str | Path) -> ExportedDetector:
    """Read a file written by :func:`export_predict` (and its ``.json`` metadata)."""
    path = Path(path)
    if not path.is_file():
        raise DataError("no exported detector", path)
    exported = jax.export.deserialize(bytearray(path.read_bytes()))
    meta_path = Path(str(path) + ".json")
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {
        "img_size": list(exported.in_avals[0].shape[1:3]), "batch_size": None}
    return ExportedDetector(exported, meta)
