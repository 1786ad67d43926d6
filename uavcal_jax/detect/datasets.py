"""Detection data sets: read any supported format, and the fixed train/validation split.

:func:`load_dataset` reads a Pascal VOC folder, a YOLO folder, a COCO json or a simulator
output folder (:mod:`.readers`, whose docstring gives the bad-input policy and coordinate
conventions) into a :class:`~uavcal_jax.detect.records.DetectionDataset`;
:func:`detect_format` tells them apart. :func:`split_ids` is the fixed split by image.

Missing folders, folders without images and unknown formats raise
:class:`~uavcal_jax.errors.DataError` naming the path.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from uavcal_jax.data.euroc_format import MAV0, TARGET_FOLDER
from uavcal_jax.detect.config import TrainConfig
from uavcal_jax.detect.readers import (
    find_coco_json,
    read_coco,
    read_sim_targets,
    read_voc,
    read_yolo,
)
from uavcal_jax.detect.records import (
    DetectionDataset,
    list_images,
    remap_classes,
    require_dir,
)
from uavcal_jax.errors import DataError

FORMATS = ("voc", "yolo", "coco", "sim")


def detect_format(path: str | Path) -> str:
    """Guess the format of a data set path: ``voc``, ``yolo``, ``coco`` or ``sim``."""
    path = require_dir(path)
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "coco"
        raise DataError("not a data set folder or COCO json", path)
    if (path / "Annotations").is_dir() and (path / "JPEGImages").is_dir():
        return "voc"
    if (path / MAV0 / TARGET_FOLDER).is_dir() or (path / TARGET_FOLDER).is_dir():
        return "sim"
    if find_coco_json(path) is not None:
        return "coco"
    if (path / "classes.txt").is_file() or any(path.glob("*.txt")) or (path / "labels").is_dir():
        return "yolo"
    if list_images(path):
        return "yolo"  # images only: all negatives
    raise DataError("cannot tell the data set format (expected VOC Annotations/+JPEGImages/, "
                    "YOLO images + .txt labels, a COCO json, or a simulator mav0/target0)",
                    path)


def load_dataset(path: str | Path, format: str | None = None, class_names=None, *,
                 check_images: bool = True) -> DetectionDataset:
    """Read a data set in ``format`` (``voc|yolo|coco|sim``; auto-detected when ``None``)."""
    path = require_dir(path)
    fmt = (format or detect_format(path)).lower()
    if fmt == "voc":
        return read_voc(path, class_names, check_images=check_images)
    if fmt == "yolo":
        return read_yolo(path, class_names, check_images=check_images)
    if fmt == "coco":
        ds = read_coco(path, check_images=check_images)
    elif fmt == "sim":
        ds = read_sim_targets(path, check_images=check_images)
    else:
        raise DataError(f"unknown data set format {format!r} (expected one of {FORMATS})", path)
    if class_names is not None and tuple(class_names) != ds.class_names:
        ds = remap_classes(ds, class_names)
    return ds


# ------------------------------------------------------------------------------ splitting


def split_ids(image_ids, val_fraction: float = TrainConfig.val_fraction,
              seed: int = TrainConfig.split_seed) -> tuple[list[str], list[str]]:
    """A fixed train/validation split by image.

    Images are ordered by ``sha1(f"{seed}:{image_id}")`` and the first
    ``round(n * val_fraction)`` (at least one when there are two or more images) go to
    validation. Deterministic across runs, machines and library versions, and mostly stable
    when images are added. Returns ``(train_ids, val_ids)``, each sorted.
    """
    ids = sorted(set(image_ids))
    n = len(ids)
    n_val = int(round(n * val_fraction))
    if val_fraction > 0 and n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    order = sorted(ids, key=lambda s: hashlib.sha1(f"{seed}:{s}".encode()).hexdigest())
    val = sorted(order[:n_val])
    train = sorted(order[n_val:])
    return train, val


def save_split(path: str | Path, train_ids, val_ids, **info) -> None:
    """Write a split as JSON: ``{"train": [...], "val": [...], **info}``."""
    Path(path).write_text(json.dumps({**info, "train": list(train_ids), "val": list(val_ids)},
                                     indent=1))
