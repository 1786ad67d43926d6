"""Batches for the detector: decode, letterbox/augment on the host, prefetch in a thread.

A :class:`DetectionLoader` turns records into fixed-shape :class:`Batch` es:

- ``images`` (B, H, W, 3) float32 RGB in [0, 1], letterboxed (pad value
  ``augment.PAD_VALUE / 255``);
- ``targets`` (B, T_max, 6) float32 rows ``[valid, class, cx, cy, w, h]`` in pixels of the
  letterboxed image (the format of :func:`uavcal_jax.detect.loss.yolo_loss`); padded rows 0;
- ``indices`` (B,) int32 record indices (-1 for the padding of a short last batch);
- ``ratios`` (B,) and ``pads`` (B, 2): a point ``p`` of the original image lands at
  ``p * ratio + pad`` (NaN for mosaics), used to map detections back.

Each epoch is a pure function of ``(seed, epoch)``: the shuffle order and every sample's
augmentation draw from ``numpy.random.default_rng([seed, epoch, position])``, so a resumed
run sees exactly the batches of an uninterrupted one, whatever the thread timing. Decoding
and augmentation run on a thread pool (OpenCV releases the GIL) and a background thread keeps
``prefetch`` batches ready while JAX trains.
"""

from __future__ import annotations

import queue
import threading
import warnings
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np

from uavcal_jax.data.detection_records import IMREAD_FLAGS, DetectionDataset, DetectionRecord
from uavcal_jax.detect.augment import (
    PAD_VALUE,
    AugmentConfig,
    augment_hsv,
    hflip,
    letterbox,
    mosaic4,
    random_affine,
    random_crop,
    resize_long_side,
    scale_boxes,
    to_gray,
)
from uavcal_jax.detect.config import DetectorConfig, TrainConfig
from uavcal_jax.errors import DataError, DataRepairWarning

#: Crop training keeps images at their stored resolution, up to this long side (pixels).
MAX_SOURCE_SIDE = 2048


class Batch(NamedTuple):
    images: np.ndarray
    targets: np.ndarray
    indices: np.ndarray
    ratios: np.ndarray
    pads: np.ndarray


def read_image_rgb(path) -> np.ndarray:
    """Decode an image file as uint8 RGB (raises DataError when it cannot be read)."""
    image = cv2.imread(str(path), IMREAD_FLAGS)
    if image is None:
        raise DataError("cannot decode image", path)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def default_max_targets(records: Sequence[DetectionRecord], mosaic: bool = False,
                        include_difficult: bool = False) -> int:
    """Room for the most boxes of any image (x4 with mosaic), a multiple of 8 (>= 8)."""
    most = max((int(np.sum(~r.difficult)) if not include_difficult else len(r)
                for r in records), default=0)
    if mosaic:
        most *= 4
    return max(8, int(np.ceil(most / 8) * 8))


class DetectionLoader:
    """Fixed-shape batches of a detection data set.

    Args:
        dataset: a :class:`DetectionDataset` or a sequence of records.
        img_size: ``(H, W)`` of the network input (``DetectorConfig``'s by default).
        batch_size: images per batch.
        augment: an :class:`AugmentConfig` for training, ``None`` for evaluation (letterbox
            only).
        shuffle: reshuffle every epoch (seeded).
        seed: the seed of shuffling and augmentation.
        max_targets: ``T_max``; default :func:`default_max_targets`. Extra boxes are dropped
            with one warning.
        drop_last: drop a short last batch (training) instead of padding it (evaluation).
        cache: keep decoded images (resized to the input's long side; with
            ``augment.crop_scale``, at their stored resolution up to :data:`MAX_SOURCE_SIDE`)
            in memory.
        workers: threads decoding/augmenting; prefetch: batches prepared ahead.
        include_difficult: put ``difficult`` boxes into the targets too.
    """

    def __init__(self, dataset: DetectionDataset | Sequence[DetectionRecord],
                 img_size: tuple[int, int] = DetectorConfig.img_size,
                 batch_size: int = TrainConfig.batch_size, *,
                 augment: AugmentConfig | None = None, shuffle: bool = False, seed: int = 0,
                 max_targets: int | None = None, drop_last: bool = False, cache: bool = True,
                 workers: int = TrainConfig.workers, prefetch: int = 2,
                 include_difficult: bool = False):
        self.records = tuple(dataset.records if isinstance(dataset, DetectionDataset)
                             else dataset)
        if not self.records:
            raise DataError("no images to load")
        self.img_size = (int(img_size[0]), int(img_size[1]))
        self.batch_size = int(batch_size)
        self.augment = augment
        #: multi-scale crops (``augment.crop_scale``): samples are ``img_size`` windows
        self.crops = augment is not None and augment.crop_scale is not None
        self.shuffle = shuffle
        self.seed = int(seed)
        self.drop_last = drop_last and len(self.records) >= self.batch_size
        self.include_difficult = include_difficult
        self.max_targets = int(max_targets or default_max_targets(
            self.records, bool(augment and augment.mosaic > 0), include_difficult))
        self.cache = cache
        self.workers = max(1, int(workers))
        self.prefetch = max(1, int(prefetch))
        self._cache: dict[int, tuple] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._truncated = False
        self.next_epoch = 0

    def __len__(self) -> int:
        n = len(self.records)
        return n // self.batch_size if self.drop_last else -(-n // self.batch_size)

    # ------------------------------------------------------------------ samples

    def load(self, index: int):
        """Record ``index`` decoded and resized to the input's long side:
        ``(image uint8 RGB, boxes, classes, ratio)``."""
        hit = self._cache.get(index)
        if hit is not None:
            return hit
        rec = self.records[index]
        image = read_image_rgb(rec.image_path)
        keep = np.ones(len(rec), bool) if self.include_difficult else ~rec.difficult
        boxes = rec.boxes[keep].astype(np.float32)
        if (image.shape[1], image.shape[0]) != (rec.width, rec.height):
            sx, sy = image.shape[1] / rec.width, image.shape[0] / rec.height
            boxes = boxes * np.array([sx, sy, sx, sy], np.float32)
        interp = cv2.INTER_LINEAR if self.augment else None
        long_side = max(self.img_size)
        if self.crops:
            long_side = min(max(image.shape[:2]), MAX_SOURCE_SIDE)
        image, boxes, ratio = resize_long_side(image, boxes, long_side, interp)
        out = (image, boxes, rec.classes[keep].astype(np.int32), ratio)
        if self.cache:
            self._cache[index] = out
        return out

    def sample(self, index: int, epoch: int = 0, position: int = 0):
        """One letterboxed (and, when training, augmented) sample:
        ``(image uint8 (H, W, 3), boxes (n, 4), classes (n,), ratio, pad)``."""
        H, W = self.img_size
        aug = self.augment
        rng = np.random.default_rng([self.seed, epoch, position])
        if self.crops:
            image, boxes, classes, _ = self.load(index)
            image, boxes, classes = random_crop(
                image, boxes, classes, rng, (H, W), scale=aug.crop_scale,
                degrees=aug.degrees, rot90=aug.rot90, on_object=aug.crop_on_object,
                min_box_px=aug.min_box_px, min_area_ratio=aug.min_area_ratio)
            ratio, pad = float("nan"), (float("nan"), float("nan"))
        elif aug is not None and aug.mosaic > 0 and rng.random() < aug.mosaic:
            others = rng.integers(0, len(self.records), 3)
            parts = [self.load(i)[:3] for i in (index, *others)]
            image, boxes, classes = mosaic4(parts, (H, W), rng)
            image, boxes, classes = random_affine(
                image, boxes, classes, rng, (H, W), scale=aug.scale, translate=aug.translate,
                degrees=aug.degrees, shear=aug.shear, min_box_px=aug.min_box_px,
                min_area_ratio=aug.min_area_ratio)
            ratio, pad = float("nan"), (float("nan"), float("nan"))
        else:
            image0, boxes0, classes, r1 = self.load(index)
            image, r2, pad = letterbox(image0, (H, W), scaleup=True)
            boxes = scale_boxes(boxes0, r2, pad)
            ratio = r1 * r2
            if aug is not None and (aug.scale or aug.translate or aug.degrees or aug.shear):
                image, boxes, classes = random_affine(
                    image, boxes, classes, rng, (H, W), scale=aug.scale,
                    translate=aug.translate, degrees=aug.degrees, shear=aug.shear,
                    min_box_px=aug.min_box_px, min_area_ratio=aug.min_area_ratio)
                ratio, pad = float("nan"), (float("nan"), float("nan"))
        if aug is not None:
            image = augment_hsv(image, rng, aug.hsv_h, aug.hsv_s, aug.hsv_v)
            if rng.random() < aug.fliplr:
                image, boxes = hflip(image, boxes)
            if aug.gray and rng.random() < aug.gray:  # no draw when off: old runs' samples
                image = to_gray(image)
        return image, boxes, classes, ratio, pad

    # ------------------------------------------------------------------ batches

    def order(self, epoch: int) -> np.ndarray:
        n = len(self.records)
        if self.shuffle:
            return np.random.default_rng([self.seed, epoch, 2**31 - 1]).permutation(n)
        return np.arange(n)

    def _make_batch(self, chunk: np.ndarray, start: int, epoch: int) -> Batch:
        H, W = self.img_size
        B, T = self.batch_size, self.max_targets
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.workers)
        samples = list(self._pool.map(lambda a: self.sample(int(a[1]), epoch, start + a[0]),
                                      enumerate(chunk)))
        images = np.full((B, H, W, 3), PAD_VALUE / 255, np.float32)
        targets = np.zeros((B, T, 6), np.float32)
        indices = np.full(B, -1, np.int32)
        ratios = np.ones(B, np.float32)
        pads = np.zeros((B, 2), np.float32)
        for j, (image, boxes, classes, ratio, pad) in enumerate(samples):
            images[j] = image.astype(np.float32) * (1 / 255)
            n = len(boxes)
            if n > T:
                if not self._truncated:
                    warnings.warn(f"an image has {n} boxes, more than max_targets={T}; the "
                                  "extra ones are dropped", DataRepairWarning, stacklevel=2)
                    self._truncated = True
                boxes, classes, n = boxes[:T], classes[:T], T
            if n:
                targets[j, :n, 0] = 1.0
                targets[j, :n, 1] = classes
                targets[j, :n, 2] = (boxes[:, 0] + boxes[:, 2]) / 2
                targets[j, :n, 3] = (boxes[:, 1] + boxes[:, 3]) / 2
                targets[j, :n, 4] = boxes[:, 2] - boxes[:, 0]
                targets[j, :n, 5] = boxes[:, 3] - boxes[:, 1]
            indices[j] = chunk[j]
            ratios[j] = ratio
            pads[j] = pad
        return Batch(images, targets, indices, ratios, pads)

    def _batches(self, epoch: int) -> Iterator[Batch]:
        order = self.order(epoch)
        for b in range(len(self)):
            start = b * self.batch_size
            yield self._make_batch(order[start:start + self.batch_size], start, epoch)

    def epoch(self, epoch: int) -> Iterator[Batch]:
        """The batches of epoch ``epoch`` (prefetched in a background thread)."""
        return _prefetch(self._batches(epoch), self.prefetch)

    def __iter__(self) -> Iterator[Batch]:
        epoch = self.next_epoch
        self.next_epoch += 1
        return self.epoch(epoch)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


_END = object()


def _prefetch(iterator: Iterator, size: int) -> Iterator:
    """Run ``iterator`` in a daemon thread, ``size`` items ahead; errors are re-raised here."""
    q: queue.Queue = queue.Queue(maxsize=size)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for item in iterator:
                if not put(item):
                    return
            put(_END)
        except BaseException as err:  # noqa: BLE001 - handed to the consumer
            put(err)

    thread = threading.Thread(target=work, daemon=True, name="detect-prefetch")
    thread.start()

    def consume():
        try:
            while True:
                item = q.get()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            stop.set()

    return consume()
