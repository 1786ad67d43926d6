"""Detections out of the program: a COCO results file, and boxes drawn on an image.

:func:`write_coco_detections` writes a COCO-format file (``images``, ``categories``,
``annotations`` with a ``score``) that ``uavcal detect eval`` and COCO tools read;
:func:`draw_detections` draws labelled boxes on a BGR image; :func:`annotate_files` runs a
detector on image files and writes both. They take the per-image
:class:`~uavcal_jax.detect.predict.ImageDetections` of
:func:`~uavcal_jax.detect.predict.detect_images`, boxes in the image's own pixels.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from uavcal_jax.data.detection_records import IMREAD_FLAGS
from uavcal_jax.detect.config import SERVE_PREDICT
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.detect.tile import TileConfig, detect
from uavcal_jax.errors import DataError, DataRepairWarning


def coco_detections(images: Sequence[dict], detections: Sequence[ImageDetections],
                    class_names: Sequence[str], category_ids: Sequence[int] | None = None,
                    info: dict | None = None) -> dict:
    """A COCO results document.

    Args:
        images: per image a dict with at least ``file_name``, ``width`` and ``height`` (other
            keys are kept); ids ``1..n`` are assigned in order.
        detections: per image, its detections (boxes ``x_min, y_min, x_max, y_max`` pixels
            become COCO ``bbox = [x, y, w, h]``, rounded to 0.01 px).
        class_names: by class id; ``category_ids[i]`` is the COCO id of class ``i``
            (default ``i``).
    """
    if category_ids is None:
        category_ids = list(range(len(class_names)))
    images_doc, anns = [], []
    for image_id, (image, det) in enumerate(zip(images, detections, strict=True), start=1):
        images_doc.append({"id": image_id, **image})
        for box, score, cls in zip(det.boxes, det.scores, det.classes, strict=True):
            bw, bh = float(box[2] - box[0]), float(box[3] - box[1])
            anns.append({"id": len(anns) + 1, "image_id": image_id,
                         "category_id": int(category_ids[int(cls)]),
                         "bbox": [round(float(box[0]), 2), round(float(box[1]), 2),
                                  round(bw, 2), round(bh, 2)],
                         "area": round(bw * bh, 2), "score": round(float(score), 5),
                         "iscrowd": 0})
    return {"info": dict(info or {}), "images": images_doc,
            "categories": [{"id": int(i), "name": n}
                           for i, n in zip(category_ids, class_names, strict=True)],
            "annotations": anns}


def write_coco_detections(path: str | Path, images: Sequence[dict],
                          detections: Sequence[ImageDetections], class_names: Sequence[str],
                          category_ids: Sequence[int] | None = None,
                          info: dict | None = None) -> dict:
    """Write :func:`coco_detections` as JSON to ``path``; returns the document."""
    doc = coco_detections(images, detections, class_names, category_ids, info)
    Path(path).write_text(json.dumps(doc))
    return doc


def draw_detections(image_bgr: np.ndarray, det: ImageDetections,
                    class_names: Sequence[str]) -> np.ndarray:
    """Boxes with "name score" labels drawn on a copy of a BGR uint8 image (one hue per
    class; line width and font scale grow with the image)."""
    out = image_bgr.copy()
    thick = max(1, round(sum(out.shape[:2]) / 600))
    for (x0, y0, x1, y1), s, c in zip(det.boxes, det.scores, det.classes, strict=True):
        hue = (int(c) * 47) % 180
        color = tuple(int(v) for v in cv2.cvtColor(
            np.uint8([[[hue, 220, 255]]]), cv2.COLOR_HSV2BGR)[0, 0])
        p0, p1 = (int(round(x0)), int(round(y0))), (int(round(x1)), int(round(y1)))
        cv2.rectangle(out, p0, p1, color, thick)
        name = class_names[int(c)] if int(c) < len(class_names) else str(int(c))
        label = f"{name} {float(s):.2f}"
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thick, 1)
        top = max(p0[1] - th - 4, 0)
        cv2.rectangle(out, (p0[0], top), (p0[0] + tw + 2, top + th + 4), color, -1)
        cv2.putText(out, label, (p0[0] + 1, top + th + 1), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * thick, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def annotate_files(predict_fn: Callable, paths: Sequence[Path], img_size: tuple[int, int],
                   out_dir: str | Path, class_names: Sequence[str], *,
                   category_ids: Sequence[int] | None = None, batch_size: int = 1,
                   info: dict | None = None, progress: Callable | None = None,
                   tile: TileConfig | None = None, max_det: int = SERVE_PREDICT.max_det
                   ) -> dict:
    """Detect objects in image files; write each image with its boxes drawn and
    ``out_dir/detections.json`` (:func:`write_coco_detections`).

    Args:
        predict_fn: ``predict_fn(images) -> Detections``, as
            :func:`~uavcal_jax.detect.predict.detect_images` takes.
        paths: the image files; each is written to ``out_dir`` under its path relative to the
            files' common folder.
        img_size: the network input ``(H, W)``.
        batch_size: images per predict call (without ``tile``).
        tile: sliced inference (:func:`uavcal_jax.detect.tile.detect_tiled`, keeping
            ``max_det`` boxes an image), ``None`` for none.
        progress: ``progress(total) -> bar`` with ``update(n)`` and ``close()`` (e.g. tqdm).

    Unreadable images are skipped with one :class:`~uavcal_jax.errors.DataRepairWarning`;
    when none can be read, :class:`~uavcal_jax.errors.DataError`. Returns ``{"out", "images",
    "detections", "skipped", "json"}``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    common_root = Path(os.path.commonpath([str(Path(p).parent) for p in paths]))
    images_doc, detections, unreadable = [], [], []
    bar = progress(len(paths)) if progress is not None else None
    for start in range(0, len(paths), batch_size):
        chunk = [Path(p) for p in paths[start:start + batch_size]]
        read = [(path, cv2.imread(str(path), IMREAD_FLAGS)) for path in chunk]
        unreadable += [str(path) for path, img in read if img is None]
        read = [(path, img) for path, img in read if img is not None]
        found = detect(predict_fn, [cv2.cvtColor(img, cv2.COLOR_BGR2RGB) for _, img in read],
                       img_size, batch_size, tile, max_det)
        for (path, img), det in zip(read, found, strict=True):
            rel = path.relative_to(common_root)
            target = out_dir / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(target), draw_detections(img, det, class_names))
            images_doc.append({"file_name": rel.as_posix(), "width": img.shape[1],
                               "height": img.shape[0], "path": str(path)})
            detections.append(det)
        if bar is not None:
            bar.update(len(chunk))
    if bar is not None:
        bar.close()
    if unreadable:
        warnings.warn(f"skipped {len(unreadable)} unreadable images: "
                      f"{', '.join(unreadable[:20])}", DataRepairWarning, stacklevel=2)
    if not images_doc:
        raise DataError("none of the images could be read", paths[0] if paths else out_dir)
    json_path = out_dir / "detections.json"
    write_coco_detections(json_path, images_doc, detections, class_names, category_ids, info)
    return {"out": str(out_dir), "images": len(images_doc),
            "detections": sum(len(d.boxes) for d in detections), "skipped": unreadable,
            "json": str(json_path)}
