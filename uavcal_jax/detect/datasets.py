"""Detection data sets for the detector: any label format in the model's class list, and the
fixed train/validation split.

:func:`load_dataset` reads a Pascal VOC folder, a YOLO folder, a COCO json or a simulator
output folder (:mod:`uavcal_jax.data.detection_labels`, whose docstring gives the bad-input
policy and coordinate conventions) into a
:class:`~uavcal_jax.data.detection_records.DetectionDataset`, expressed in a given class list
(:func:`remap_classes`); :func:`concat_datasets` joins several (e.g. simulated flights) into
one. :func:`split_ids` is the fixed split by image.

Missing folders, folders without images and unknown formats raise
:class:`~uavcal_jax.errors.DataError` naming the path.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from uavcal_jax.data.detection_labels import (
    LABEL_FORMATS,
    detect_format,
    has_yolo_class_list,
    read_coco,
    read_sim_targets,
    read_voc,
    read_yolo,
)
from uavcal_jax.data.detection_records import DetectionDataset, DetectionRecord, require_dir
from uavcal_jax.detect.config import TrainConfig
from uavcal_jax.errors import DataError

#: Class names that mean one of the detector's classes (lower case): the vehicle types of
#: aerial sets (KIT's truck, bus and minibus; VisDrone's van, truck and bus) are ``car``,
#: their walkers ``person``. Used only when the target list lacks the name itself.
CLASS_ALIASES = {
    "truck": "car", "bus": "car", "minibus": "car", "van": "car", "vehicle": "car",
    "pickup": "car", "suv": "car", "pedestrian": "person", "people": "person",
}


def class_index(name: str, class_names) -> int:
    """Index of ``name`` in ``class_names``: exactly, else ignoring case, else through
    :data:`CLASS_ALIASES`; -1 when none matches."""
    lowered = [n.lower() for n in class_names]
    for candidate in (name, name.lower(), CLASS_ALIASES.get(name.lower())):
        if candidate in class_names:
            return tuple(class_names).index(candidate)
        if candidate is not None and candidate.lower() in lowered:
            return lowered.index(candidate.lower())
    return -1


def remap_classes(ds: DetectionDataset, class_names) -> DetectionDataset:
    """Express ``ds`` in another class list (by name, see :func:`class_index`); boxes of other
    classes are dropped (their images stay, as negatives where nothing is left)."""
    class_names = tuple(class_names)
    lut = np.array([class_index(n, class_names) for n in ds.class_names] + [-1],
                   dtype=np.int32)
    records = []
    for r in ds.records:
        new = lut[r.classes] if len(r.classes) else r.classes
        keep = new >= 0
        records.append(DetectionRecord(r.image_path, r.boxes[keep], new[keep].astype(np.int32),
                                       r.difficult[keep], r.width, r.height, r.image_id))
    return DetectionDataset(tuple(records), class_names, ds.root, ds.format)


def load_dataset(path: str | Path, format: str | None = None, class_names=None, *,
                 check_images: bool = True) -> DetectionDataset:
    """Read a data set in ``format`` (``voc|yolo|coco|sim``; auto-detected when ``None``),
    expressed in ``class_names`` when given (:func:`remap_classes`: by name, ignoring case,
    through :data:`CLASS_ALIASES`; e.g. an aerial set's trucks and buses become ``car``)."""
    path = require_dir(path)
    fmt = (format or detect_format(path)).lower()
    if fmt == "voc":  # by the annotations' own names, then remapped (aliases apply)
        ds = read_voc(path, check_images=check_images)
    elif fmt == "yolo":
        # a folder's own classes.txt names its ids; the model's list only stands in for it
        # when it has none
        ds = read_yolo(path, None if has_yolo_class_list(path) else class_names,
                       check_images=check_images)
    elif fmt == "coco":
        ds = read_coco(path, check_images=check_images)
    elif fmt == "sim":
        ds = read_sim_targets(path, check_images=check_images)
    else:
        raise DataError(f"unknown data set format {format!r} (expected one of "
                        f"{LABEL_FORMATS})", path)
    if class_names is not None and tuple(class_names) != ds.class_names:
        ds = remap_classes(ds, class_names)
    return ds


def concat_datasets(parts: Sequence[tuple[str, DetectionDataset]]) -> DetectionDataset:
    """One data set of several ``(name, dataset)`` parts, e.g. simulated flights.

    Image ids become ``"<name>/<image_id>"`` (each flight's ``cam0/<t>.png`` would collide
    otherwise), so names must be unique. Every part is expressed in the first part's class
    list (:func:`remap_classes`); the root is the parts' common folder and the format is
    theirs when they share one, else ``"mixed"``.
    """
    if not parts:
        raise ValueError("concat_datasets needs at least one data set")
    names = [n for n, _ in parts]
    if len(set(names)) != len(names):
        raise ValueError(f"data set names must be unique, got {names}")
    class_names = parts[0][1].class_names
    records = []
    for name, ds in parts:
        if ds.class_names != class_names:
            ds = remap_classes(ds, class_names)
        records += [replace(r, image_id=f"{name}/{r.image_id}") for r in ds.records]
    roots = [str(Path(ds.root).absolute()) for _, ds in parts]
    formats = {ds.format for _, ds in parts}
    return DetectionDataset(tuple(records), class_names, Path(os.path.commonpath(roots)),
                            formats.pop() if len(formats) == 1 else "mixed",
                            parts[0][1].category_ids)


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
