"""Detection data sets: Pascal VOC XML, YOLO txt, COCO json and the simulator's target labels.

Every reader returns a :class:`DetectionDataset`: a tuple of :class:`DetectionRecord` (one per
image: its path, its boxes as ``x_min, y_min, x_max, y_max`` in pixels of the *original*
image, class ids, and a ``difficult`` flag) plus the class names (class id ``i`` is
``class_names[i]``).

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

Missing folders, folders without images and unknown formats raise
:class:`~uavcal_jax.errors.DataError` naming the path.
"""

from __future__ import annotations

import hashlib
import json
import sys
import warnings
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from uavcal_jax.errors import DataError, DataRepairWarning

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
FORMATS = ("voc", "yolo", "coco", "sim")

#: imread flags used everywhere (the raw pixel grid: EXIF orientation is not applied, so
#: boxes drawn on the stored pixels stay valid).
IMREAD_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


@dataclass(frozen=True)
class DetectionRecord:
    """One image and its labels.

    Attributes:
        image_path: the image file.
        boxes: (n, 4) float32 ``x_min, y_min, x_max, y_max`` pixels of the original image.
        classes: (n,) int32 class ids.
        difficult: (n,) bool; VOC ``difficult`` / COCO ``iscrowd`` (ignored in training and
            treated as "ignore" ground truth by the mAP).
        width, height: the image size in pixels.
        image_id: the image's name relative to the data set root (POSIX), used for splits and
            COCO output.
    """

    image_path: Path
    boxes: np.ndarray
    classes: np.ndarray
    difficult: np.ndarray
    width: int
    height: int
    image_id: str

    def __len__(self) -> int:
        return int(self.boxes.shape[0])


@dataclass(frozen=True)
class DetectionDataset:
    """Records plus class names; ``category_ids[i]`` is the external (COCO) id of class ``i``."""

    records: tuple[DetectionRecord, ...]
    class_names: tuple[str, ...]
    root: Path
    format: str
    category_ids: tuple[int, ...] = field(default=())

    def __post_init__(self):
        if not self.category_ids:
            object.__setattr__(self, "category_ids", tuple(range(len(self.class_names))))

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self):
        return iter(self.records)

    def __getitem__(self, i: int) -> DetectionRecord:
        return self.records[i]

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def num_boxes(self) -> int:
        return sum(len(r) for r in self.records)

    @property
    def image_ids(self) -> list[str]:
        return [r.image_id for r in self.records]

    def subset(self, image_ids) -> DetectionDataset:
        """The records whose ``image_id`` is in ``image_ids``, in this data set's order."""
        wanted = set(image_ids)
        missing = wanted - set(self.image_ids)
        if missing:
            raise DataError(f"{len(missing)} images of the split are not in the data set, "
                            f"e.g. {sorted(missing)[:3]}", self.root)
        return DetectionDataset(tuple(r for r in self.records if r.image_id in wanted),
                                self.class_names, self.root, self.format, self.category_ids)


class _Problems:
    """Collects everything a reader skipped or repaired; emits one warning at the end."""

    def __init__(self, where: Path):
        self.where = where
        self.images: list[str] = []
        self.labels: list[str] = []
        self.clipped = 0
        self.outside: list[str] = []

    def warn(self) -> None:
        parts = []

        def listing(items):
            more = f" (+{len(items) - 20} more)" if len(items) > 20 else ""
            return "; ".join(items[:20]) + more

        if self.images:
            parts.append(f"skipped {len(self.images)} unreadable images/annotation files: "
                         f"{listing(self.images)}")
        if self.labels:
            parts.append(f"skipped {len(self.labels)} malformed labels: {listing(self.labels)}")
        if self.outside:
            parts.append(f"dropped {len(self.outside)} boxes outside their image: "
                         f"{listing(self.outside)}")
        if self.clipped:
            parts.append(f"clipped {self.clipped} boxes to their image")
        if parts:
            warnings.warn(f"{self.where}: " + ", ".join(parts), DataRepairWarning,
                          stacklevel=_caller_stacklevel())


def _caller_stacklevel() -> int:
    """The stack level of the first frame outside this module (for ``warnings.warn``)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename == __file__:
        frame, level = frame.f_back, level + 1
    return level


def image_size(path: Path, check: bool = True) -> tuple[int, int] | None:
    """``(width, height)`` of an image, or ``None`` if it cannot be read.

    With ``check`` the whole image is decoded (catches corrupt files); otherwise only the
    header is read (PIL).
    """
    if check:
        try:
            image = cv2.imread(str(path), IMREAD_FLAGS)
        except cv2.error:
            return None
        if image is None or image.size == 0:
            return None
        return int(image.shape[1]), int(image.shape[0])
    try:
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception:  # noqa: BLE001 - any failure means unreadable
        return None


def _sizes(paths: list[Path], check: bool) -> list[tuple[int, int] | None]:
    if len(paths) < 8:
        return [image_size(p, check) for p in paths]
    with ThreadPoolExecutor(max_workers=4) as pool:
        return list(pool.map(lambda p: image_size(p, check), paths))


def _finish_boxes(boxes: list, classes: list, difficult: list, width: int, height: int,
                  name: str, problems: _Problems):
    """Clip boxes to the image, drop empty ones, build arrays."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    c = np.asarray(classes, dtype=np.int32).reshape(-1)
    d = np.asarray(difficult, dtype=bool).reshape(-1)
    if len(b):
        clipped = b.copy()
        clipped[:, [0, 2]] = np.clip(clipped[:, [0, 2]], 0.0, width)
        clipped[:, [1, 3]] = np.clip(clipped[:, [1, 3]], 0.0, height)
        changed = np.any(np.abs(clipped - b) > 1.0, axis=1)  # sub-pixel: silent
        keep = (clipped[:, 2] - clipped[:, 0] > 0) & (clipped[:, 3] - clipped[:, 1] > 0)
        problems.clipped += int(np.sum(changed & keep))
        for i in np.flatnonzero(~keep):
            problems.outside.append(f"{name} box {i + 1}")
        b, c, d = clipped[keep], c[keep], d[keep]
    return b.astype(np.float32), c, d


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*")
                  if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
                  and not any(part.startswith(".") for part in p.relative_to(folder).parts))


def _require_dir(root: str | Path) -> Path:
    root = Path(root)
    if not root.exists():
        raise DataError("no such data folder", root)
    return root


def _read_class_list(path: Path) -> tuple[str, ...]:
    return tuple(line.strip() for line in path.read_text().splitlines() if line.strip())


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
    root = _require_dir(root)
    ann_dir, img_dir = root / "Annotations", root / "JPEGImages"
    if not ann_dir.is_dir():
        raise DataError("not a VOC folder (no Annotations/)", root)
    if not img_dir.is_dir():
        raise DataError("not a VOC folder (no JPEGImages/)", root)
    problems = _Problems(root)
    images = _list_images(img_dir)
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
    sizes = _sizes(images, check_images)
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
        b, c, d = _finish_boxes(boxes, classes, difficult, size[0], size[1], name, problems)
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


def read_yolo(root: str | Path, class_names=None, *, check_images: bool = True
              ) -> DetectionDataset:
    """A YOLO folder: images beside same-named ``.txt`` files (``class cx cy w h``, normalised)
    and ``classes.txt`` (one name per line). The ultralytics layout (``images/`` and
    ``labels/`` side by side, names in ``classes.txt`` at the root) is read too.

    Without ``classes.txt`` (and no ``class_names``) the classes are named by their ids.
    Images without a label file, or with an empty one, are negatives.
    """
    root = _require_dir(root)
    if class_names is None:
        for candidate in (root / "classes.txt", root / "labels" / "classes.txt"):
            if candidate.is_file():
                class_names = _read_class_list(candidate)
                break
    images = _list_images(root)
    if not images:
        raise DataError("no images found", root)
    problems = _Problems(root)
    sizes = _sizes(images, check_images)
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
        b, c, d = _finish_boxes(boxes, classes, [False] * len(rows), w_img, h_img, name,
                                problems)
        records.append(DetectionRecord(path, b, c, d, w_img, h_img, name))
    problems.warn()
    return DetectionDataset(tuple(records), tuple(class_names), root, "yolo")


# ----------------------------------------------------------------------------------- COCO


def _find_coco_json(root: Path) -> Path | None:
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
    path = _require_dir(path)
    if path.is_dir():
        found = _find_coco_json(path)
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
    problems = _Problems(json_path)
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
    sizes = _sizes(paths, check_images)
    records = []
    for im, path, size in zip(images, paths, sizes, strict=True):
        name = str(im["file_name"])
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        rows = anns.get(im.get("id"), [])
        b, c, d = _finish_boxes([r[0] for r in rows], [r[1] for r in rows],
                                [r[2] for r in rows], size[0], size[1], name, problems)
        records.append(DetectionRecord(path, b, c, d, size[0], size[1], name))
    problems.warn()
    return DetectionDataset(tuple(records), class_names, image_root, "coco", category_ids)


# ------------------------------------------------------------------------ simulator targets


def read_sim_targets(root: str | Path, camera: str = "cam0", *, stride: int = 1,
                     check_images: bool = True) -> DetectionDataset:
    """The simulator's rendered frames with their target boxes (``mav0/target0``).

    Every ``stride``-th frame of ``camera`` is a record; frames without targets are negatives.
    """
    from uavcal_jax.data.targets import read_target_labels

    root = _require_dir(root)
    mav0 = root / "mav0" if (root / "mav0").is_dir() else root
    labels = read_target_labels(mav0 / "target0")
    cam_dir = mav0 / camera
    csv_path = cam_dir / "data.csv"
    if not csv_path.is_file():
        raise DataError("missing camera data.csv", csv_path)
    problems = _Problems(mav0)
    frames = []
    for line in csv_path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) >= 2 and fields[0].isdigit():
            frames.append((int(fields[0]), fields[1]))
    frames = frames[::max(1, int(stride))]
    if not frames:
        raise DataError("no frames listed", csv_path)
    paths = [cam_dir / "data" / f for _, f in frames]
    sizes = _sizes(paths, check_images)
    records = []
    for (t_ns, fname), path, size in zip(frames, paths, sizes, strict=True):
        name = f"{camera}/{fname}"
        if size is None:
            problems.images.append(f"{name} (cannot decode)")
            continue
        rows = labels.for_frame(t_ns, camera)
        b, c, d = _finish_boxes(rows.box, rows.class_id, np.zeros(len(rows), bool), size[0],
                                size[1], name, problems)
        records.append(DetectionRecord(path, b, c, d, size[0], size[1], name))
    problems.warn()
    return DetectionDataset(tuple(records), labels.class_names, mav0, "sim")


# ----------------------------------------------------------------------- format detection


def detect_format(path: str | Path) -> str:
    """Guess the format of a data set path: ``voc``, ``yolo``, ``coco`` or ``sim``."""
    path = _require_dir(path)
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "coco"
        raise DataError("not a data set folder or COCO json", path)
    if (path / "Annotations").is_dir() and (path / "JPEGImages").is_dir():
        return "voc"
    if (path / "mav0" / "target0").is_dir() or (path / "target0").is_dir():
        return "sim"
    if _find_coco_json(path) is not None:
        return "coco"
    if (path / "classes.txt").is_file() or any(path.glob("*.txt")) or (path / "labels").is_dir():
        return "yolo"
    if _list_images(path):
        return "yolo"  # images only: all negatives
    raise DataError("cannot tell the data set format (expected VOC Annotations/+JPEGImages/, "
                    "YOLO images + .txt labels, a COCO json, or a simulator mav0/target0)",
                    path)


def load_dataset(path: str | Path, format: str | None = None, class_names=None, *,
                 check_images: bool = True) -> DetectionDataset:
    """Read a data set in ``format`` (``voc|yolo|coco|sim``; auto-detected when ``None``)."""
    path = _require_dir(path)
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


def remap_classes(ds: DetectionDataset, class_names) -> DetectionDataset:
    """Express ``ds`` in another class list (by name); boxes of other classes are dropped."""
    class_names = tuple(class_names)
    index = {n: i for i, n in enumerate(class_names)}
    lut = np.array([index.get(n, -1) for n in ds.class_names] + [-1], dtype=np.int32)
    records = []
    for r in ds.records:
        new = lut[r.classes] if len(r.classes) else r.classes
        keep = new >= 0
        records.append(DetectionRecord(r.image_path, r.boxes[keep], new[keep].astype(np.int32),
                                       r.difficult[keep], r.width, r.height, r.image_id))
    return DetectionDataset(tuple(records), class_names, ds.root, ds.format)


# ------------------------------------------------------------------------------ splitting


def split_ids(image_ids, val_fraction: float = 0.2, seed: int = 0
              ) -> tuple[list[str], list[str]]:
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


def load_split(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise DataError("missing split file", path)
    return json.loads(path.read_text())
