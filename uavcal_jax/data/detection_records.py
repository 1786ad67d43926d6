"""Labelled images (detection records and data sets), and the bookkeeping every label reader
of :mod:`uavcal_jax.data.detection_labels` shares.

A :class:`DetectionDataset` is a tuple of :class:`DetectionRecord` (one per image: its path,
its boxes as ``x_min, y_min, x_max, y_max`` in pixels of the *original* image, class ids, and
a ``difficult`` flag) plus the class names (class id ``i`` is ``class_names[i]``).
:class:`Problems` collects what a reader skipped or repaired and emits one
:class:`~uavcal_jax.errors.DataRepairWarning`; :func:`finish_boxes` clips boxes to their image.
:func:`list_images` and :func:`collect_images` find image files; :data:`IMREAD_FLAGS` is how
every image is decoded.
"""

from __future__ import annotations

import glob
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from uavcal_jax.data.image_header import image_size
from uavcal_jax.errors import DataError, DataRepairWarning

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")

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


class Problems:
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


#: The modules whose frames a warning skips, to point at the caller of a reader.
_READER_MODULES = ("uavcal_jax.data.detection_records", "uavcal_jax.data.detection_labels",
                   "uavcal_jax.detect.datasets")


def _caller_stacklevel() -> int:
    """The stack level of the first frame outside the readers (for ``warnings.warn``)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_globals.get("__name__") in _READER_MODULES:
        frame, level = frame.f_back, level + 1
    return level


def _image_size(path: Path, check: bool = True) -> tuple[int, int] | None:
    """``(width, height)`` of an image, or ``None`` if it cannot be read.

    With ``check`` the whole image is decoded (catches corrupt files); otherwise only the
    header is read (:func:`uavcal_jax.data.image_header.image_size`).
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
        return image_size(path)
    except DataError:
        return None


def image_sizes(paths: list[Path], check: bool) -> list[tuple[int, int] | None]:
    """:func:`_image_size` of each path (threads: OpenCV releases the GIL)."""
    if len(paths) < 8:
        return [_image_size(p, check) for p in paths]
    with ThreadPoolExecutor(max_workers=4) as pool:
        return list(pool.map(lambda p: _image_size(p, check), paths))


def finish_boxes(boxes: list, classes: list, difficult: list, width: int, height: int,
                  name: str, problems: Problems):
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


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*")
                  if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
                  and not any(part.startswith(".") for part in p.relative_to(folder).parts))


def require_dir(root: str | Path) -> Path:
    root = Path(root)
    if not root.exists():
        raise DataError("no such data folder", root)
    return root


def read_class_list(path: Path) -> tuple[str, ...]:
    return tuple(line.strip() for line in path.read_text().splitlines() if line.strip())


def collect_images(items) -> list[Path]:
    """Files, folders (recursive) and glob patterns -> a sorted list of image paths."""
    found: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found += [p for p in sorted(path.rglob("*")) if p.suffix.lower() in IMAGE_SUFFIXES]
        elif path.is_file():
            found.append(path)
        elif any(c in item for c in "*?["):
            found += [Path(p) for p in sorted(glob.glob(item, recursive=True))
                      if Path(p).suffix.lower() in IMAGE_SUFFIXES]
        else:
            raise DataError("no such image file or folder", path)
    unique = list(dict.fromkeys(p.resolve() for p in found))
    if not unique:
        raise DataError("no images found", " ".join(items))
    return unique
