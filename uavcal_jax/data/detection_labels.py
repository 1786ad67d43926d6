"""Detection label formats: Pascal VOC XML, YOLO txt, COCO json and the simulator's targets.

Every reader returns a :class:`~uavcal_jax.data.detection_records.DetectionDataset`;
:func:`detect_format` tells the formats (:data:`LABEL_FORMATS`) apart by the path.

Bad input policy (one :class:`~uavcal_jax.errors.DataRepairWarning` per read, listing what
was done):

- unreadable or corrupt images, and annotation files that cannot be parsed, are skipped
  (the whole image: its labels are unknown);
- malformed labels (wrong field count, non-numbers, non-finite values, empty or negative
  width/height, class ids outside the class list, unknown VOC class names when a class list
  is given) are skipped, the rest of the image is kept;
- boxes that stick out of the image are clipped to it (reported when they move by more than
  one pixel); boxes wholly outside are dropped;
- images without a label file, or with an empty one, are valid negatives.

Coordinate conventions: VOC's ``xmin..xmax`` are 1-based inclusive pixel indices, so a box
becomes ``[xmin - 1, ymin - 1, xmax, ymax]`` in continuous pixel coordinates (as detectron2
reads VOC). YOLO rows are ``class cx cy w h`` normalised by the image size. COCO ``bbox`` is
``[x, y, w, h]`` in pixels; its category ids are mapped to contiguous ids in sorted id order
(``DetectionDataset.category_ids`` keeps the original ids). VOC ``difficult`` objects and COCO
``iscrowd`` annotations are kept with ``difficult=True``: training ignores them and the mAP
treats them as "ignore" ground truth (a detection matched to one is neither a true nor a
false positive).

Missing folders and folders without images raise :class:`~uavcal_jax.errors.DataError`
naming the path.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from uavcal_jax.data.detection_records import (
    DetectionDataset,
    DetectionRecord,
    Problems,
    finish_boxes,
    image_sizes,
    list_images,
    read_class_list,
    require_dir,
)
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.euroc_format import DATA_CSV, MAV0, TARGET_FOLDER
from uavcal_jax.errors import DataError

#: The label formats :func:`detect_format` tells apart: Pascal VOC, YOLO, COCO and the
#: simulator's ``target0``.
LABEL_FORMATS = ("voc", "yolo", "coco", "sim")

# ----------------------------------------------------------------------------------- VOC


def read_voc(root: str | Path, class_names=None, *, check_images: bool = True
             ) -> DetectionDataset:
    """A Pascal VOC folder: ``Annotations/*.xml`` and ``JPEGImages/``.

    Args:
        root: the folder holding ``Annotations`` and ``JPEGImages``.
        class_names: the class list; by default the sorted set of object names in the
            annotations. With a list, objects of other names are skipped (and listed).
        check_images: decode every image once to catch corrupt files.

    Images in ``JPEGImages`` without an annotation file are negatives.
    """
    root = require_dir(root)
    ann_dir, img_dir = root / "Annotations", root / "JPEGImages"
    if not ann_dir.is_dir():
        raise DataError("not a VOC folder (no Annotations/)", root)
    if not img_dir.is_dir():
        raise DataError("not a VOC folder (no JPEGImages/)", root)
    problems = Problems(root)
    images = list_images(img_dir)
    by_stem = {}
    for p in images:
        by_stem.setdefault(p.relative_to(img_dir).with_suffix("").as_posix(), p)

    parsed = {}  # image path -> list of (name, box, difficult)
    for xml_path in sorted(ann_dir.rglob("*.xml")):
        rel = xml_path.relative_to(ann_dir).with_suffix("").as_posix()
        try:
            tree = ET.parse(xml_path).getroot()
        except (ET.ParseError, OSError) as err:
            problems.images.append(f"{xml_path.name} ({err})")
            image = by_stem.get(rel)
            if image is not None:
                parsed[image] = None  # unknown labels: skip the image
            continue
        filename = (tree.findtext("filename") or "").strip()
        image = None
        if filename and (img_dir / filename).is_file():
            image = img_dir / filename
        elif rel in by_stem:
            image = by_stem[rel]
        elif filename and Path(filename).stem in by_stem:
            image = by_stem[Path(filename).stem]
        if image is None:
            problems.images.append(f"{xml_path.name} (image {filename or rel} not found)")
            continue
        objects = []
        for k, obj in enumerate(tree.iter("object"), start=1):
            label = f"{xml_path.name} object {k}"
            name = (obj.findtext("name") or "").strip()
            box = obj.find("bndbox")
            try:
                if not name:
                    raise ValueError("no name")
                if box is None:
                    raise ValueError("no bndbox")
                x0, y0, x1, y1 = (float(box.findtext(tag)) for tag in
                                  ("xmin", "ymin", "xmax", "ymax"))
                if not np.all(np.isfinite([x0, y0, x1, y1])):
                    raise ValueError("non-finite coordinate")
                if x1 < x0 or y1 < y0:
                    raise ValueError("xmax < xmin or ymax < ymin")
                diff = obj.findtext("difficult")
                difficult = bool(int(float(diff))) if diff and diff.strip() else False
            except (TypeError, ValueError) as err:
                problems.labels.append(f"{label} ({err})")
                continue
            objects.append((name, [x0 - 1.0, y0 - 1.0, x1, y1], difficult))
        parsed[image] = objects

    if class_names is None:
        class_names = tuple(sorted({o[0] for objs in parsed.values() if objs for o in objs}))
    class_names = tuple(class_names)
    index = {n: i for i, n in enumerate(class_names)}

    if not images:
        raise DataError("no images found", img_dir)
    sizes = image_sizes(images, check_images)
    records = []
    for path, size in zip(images, sizes, strict=True):
        name = path.relative_to(img_dir).as_posix()
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        objects = parsed.get(path, [])
        if objects is None:
            continue
        boxes, classes, difficult = [], [], []
        for k, (cname, box, diff) in enumerate(objects, start=1):
            if cname not in index:
                problems.labels.append(f"{name} object {k} (class {cname!r} not in the list)")
                continue
            boxes.append(box)
            classes.append(index[cname])
            difficult.append(diff)
        b, c, d = finish_boxes(boxes, classes, difficult, size[0], size[1], name, problems)
        records.append(DetectionRecord(path, b, c, d, size[0], size[1], name))
    problems.warn()
    return DetectionDataset(tuple(records), class_names, root, "voc")


# ----------------------------------------------------------------------------------- YOLO


def _yolo_label_path(image: Path, root: Path) -> Path:
    beside = image.with_suffix(".txt")
    if beside.is_file():
        return beside
    # ultralytics layout: root/images/... <-> root/labels/...
    try:
        rel = image.relative_to(root / "images")
    except ValueError:
        return beside
    return (root / "labels" / rel).with_suffix(".txt")


def _yolo_class_list(root: Path) -> Path | None:
    for candidate in (root / "classes.txt", root / "labels" / "classes.txt"):
        if candidate.is_file():
            return candidate
    return None


def has_yolo_class_list(root: str | Path) -> bool:
    """Whether the YOLO folder ``root`` names its classes (``classes.txt``)."""
    return _yolo_class_list(Path(root)) is not None


def read_yolo(root: str | Path, class_names=None, *, check_images: bool = True
              ) -> DetectionDataset:
    """A YOLO folder: images beside same-named ``.txt`` files (``class cx cy w h``, normalised)
    and ``classes.txt`` (one name per line). The ultralytics layout (``images/`` and
    ``labels/`` side by side, names in ``classes.txt`` at the root) is read too.

    Without ``classes.txt`` (and no ``class_names``) the classes are named by their ids.
    Images without a label file, or with an empty one, are negatives.
    """
    root = require_dir(root)
    if class_names is None and has_yolo_class_list(root):
        class_names = read_class_list(_yolo_class_list(root))
    images = list_images(root)
    if not images:
        raise DataError("no images found", root)
    problems = Problems(root)
    sizes = image_sizes(images, check_images)
    rows_per_image = []
    max_class = -1
    for path in images:
        name = path.relative_to(root).as_posix()
        label_path = _yolo_label_path(path, root)
        rows = []
        if label_path.is_file():
            try:
                text = label_path.read_text()
            except (OSError, UnicodeDecodeError) as err:
                problems.images.append(f"{label_path.name} ({err})")
                rows_per_image.append(None)
                continue
            for lineno, line in enumerate(text.splitlines(), start=1):
                if not line.strip():
                    continue
                fields = line.split()
                try:
                    if len(fields) != 5:
                        raise ValueError(f"{len(fields)} fields, expected 5")
                    cls_f = float(fields[0])
                    if cls_f != int(cls_f) or cls_f < 0:
                        raise ValueError(f"class {fields[0]} is not an id")
                    cx, cy, w, h = map(float, fields[1:])
                    if not np.all(np.isfinite([cx, cy, w, h])):
                        raise ValueError("non-finite value")
                    if w <= 0 or h <= 0:
                        raise ValueError("width or height <= 0")
                    if class_names is not None and int(cls_f) >= len(class_names):
                        raise ValueError(f"class {int(cls_f)} not in classes.txt")
                except ValueError as err:
                    problems.labels.append(f"{label_path.name} line {lineno} ({err})")
                    continue
                rows.append((int(cls_f), cx, cy, w, h))
                max_class = max(max_class, int(cls_f))
        rows_per_image.append(rows)
    if class_names is None:
        class_names = tuple(str(i) for i in range(max_class + 1))
    records = []
    for path, size, rows in zip(images, sizes, rows_per_image, strict=True):
        name = path.relative_to(root).as_posix()
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        if rows is None:
            continue
        w_img, h_img = size
        boxes = [[(cx - w / 2) * w_img, (cy - h / 2) * h_img, (cx + w / 2) * w_img,
                  (cy + h / 2) * h_img] for _, cx, cy, w, h in rows]
        classes = [r[0] for r in rows]
        b, c, d = finish_boxes(boxes, classes, [False] * len(rows), w_img, h_img, name,
                                problems)
        records.append(DetectionRecord(path, b, c, d, w_img, h_img, name))
    problems.warn()
    return DetectionDataset(tuple(records), tuple(class_names), root, "yolo")


# ----------------------------------------------------------------------------------- COCO


def find_coco_json(root: Path) -> Path | None:
    candidates = sorted(root.glob("*.json")) + sorted(root.glob("annotations/*.json"))
    for path in candidates:
        try:
            with open(path) as f:
                head = json.load(f)
        except (OSError, ValueError):
            continue
        if isinstance(head, dict) and "images" in head and "annotations" in head:
            return path
    return None


def read_coco(path: str | Path, image_root: str | Path | None = None, *,
              check_images: bool = True) -> DetectionDataset:
    """A COCO detection json (``images``, ``annotations``, ``categories``).

    Args:
        path: the json file, or a folder holding one (directly or under ``annotations/``).
        image_root: where ``file_name`` is resolved; by default the first of
            ``<json dir>/images``, ``<json dir>``, ``<json dir>/..``, ``<json dir>/../images``
            that holds the first image.
    """
    path = require_dir(path)
    if path.is_dir():
        found = find_coco_json(path)
        if found is None:
            raise DataError("no COCO json (with images and annotations) found", path)
        json_path = found
    else:
        json_path = path
    try:
        with open(json_path) as f:
            data = json.load(f)
    except (OSError, ValueError) as err:
        raise DataError(f"cannot read COCO json ({err})", json_path) from err
    if not isinstance(data, dict) or "images" not in data:
        raise DataError("not a COCO json (no 'images')", json_path)
    problems = Problems(json_path)
    categories = sorted(data.get("categories", []), key=lambda c: c["id"])
    if categories:
        category_ids = tuple(int(c["id"]) for c in categories)
        class_names = tuple(str(c.get("name", c["id"])) for c in categories)
    else:
        ids = sorted({int(a["category_id"]) for a in data.get("annotations", [])})
        category_ids, class_names = tuple(ids), tuple(str(i) for i in ids)
    cat_index = {c: i for i, c in enumerate(category_ids)}
    images = [im for im in data["images"] if isinstance(im, dict) and "file_name" in im]
    if not images:
        raise DataError("no images listed", json_path)
    if image_root is None:
        base = json_path.parent
        options = [base / "images", base, base.parent, base.parent / "images"]
        image_root = next((o for o in options if (o / images[0]["file_name"]).is_file()),
                          options[0] if options[0].is_dir() else base)
    image_root = Path(image_root)
    anns: dict = {}
    for k, ann in enumerate(data.get("annotations", []), start=1):
        label = f"annotation {ann.get('id', k) if isinstance(ann, dict) else k}"
        try:
            x, y, w, h = (float(v) for v in ann["bbox"])
            if not np.all(np.isfinite([x, y, w, h])):
                raise ValueError("non-finite bbox")
            if w <= 0 or h <= 0:
                raise ValueError("width or height <= 0")
            cat = int(ann["category_id"])
            if cat not in cat_index:
                raise ValueError(f"category {cat} not in categories")
            anns.setdefault(ann["image_id"], []).append(
                ([x, y, x + w, y + h], cat_index[cat], bool(ann.get("iscrowd", 0))))
        except (KeyError, TypeError, ValueError) as err:
            problems.labels.append(f"{label} ({err})")
    paths = [image_root / im["file_name"] for im in images]
    sizes = image_sizes(paths, check_images)
    records = []
    for im, path, size in zip(images, paths, sizes, strict=True):
        name = str(im["file_name"])
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        rows = anns.get(im.get("id"), [])
        b, c, d = finish_boxes([r[0] for r in rows], [r[1] for r in rows],
                                [r[2] for r in rows], size[0], size[1], name, problems)
        records.append(DetectionRecord(path, b, c, d, size[0], size[1], name))
    problems.warn()
    return DetectionDataset(tuple(records), class_names, image_root, "coco", category_ids)


# ------------------------------------------------------------------------ simulator targets


def read_sim_targets(root: str | Path, camera: str = "cam0", *, stride: int = 1,
                     check_images: bool = True) -> DetectionDataset:
    """The simulator's rendered frames with their target boxes (``mav0/target0``).

    The recording is read with :func:`~uavcal_jax.data.euroc.read_euroc`, so the EuRoC reader's
    bad-input rules apply to the frame list (malformed or out-of-order ``data.csv`` rows,
    listed frames whose image is missing) and to the target labels. Every ``stride``-th
    frame of ``camera`` is a record; frames without targets are negatives.
    """
    root = require_dir(root)
    sequence = read_euroc(root)
    mav0 = root / MAV0 if (root / MAV0).is_dir() else root
    if sequence.targets is None:
        raise DataError(f"no target labels ({TARGET_FOLDER} folder)", mav0 / TARGET_FOLDER)
    stream = sequence.camera(camera)
    frames = range(0, len(stream), max(1, int(stride)))
    if not frames:
        raise DataError("no frames listed", mav0 / camera / DATA_CSV)
    paths = [stream.paths[i] for i in frames]
    sizes = image_sizes(paths, check_images)
    problems = Problems(mav0)
    records = []
    for i, path, size in zip(frames, paths, sizes, strict=True):
        name = f"{camera}/{path.name}"
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        rows = sequence.targets.for_frame(int(stream.t_ns[i]), camera)
        b, c, d = finish_boxes(rows.box, rows.class_id, np.zeros(len(rows), bool), size[0],
                               size[1], name, problems)
        records.append(DetectionRecord(path, b, c, d, size[0], size[1], name))
    problems.warn()
    return DetectionDataset(tuple(records), sequence.targets.class_names, mav0, "sim")


# ------------------------------------------------------------------------------ format


def detect_format(path: str | Path) -> str:
    """Guess the label format of a data set path: one of :data:`LABEL_FORMATS`."""
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
