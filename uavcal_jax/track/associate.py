"""Frame-to-frame association of detections into tracks (the choice of the target to follow
among them is :mod:`uavcal_jax.track.chain`).

Plain NumPy (detections vary in number per frame). Each track predicts its box one frame on
with the box's last velocity (constant velocity in the image, so two targets crossing keep
their ids); detections are matched to the predictions of the same class by the Hungarian
assignment on IoU (``scipy.optimize.linear_sum_assignment``), pairs below ``min_iou`` are not
matched. Unmatched detections start new tracks; a track unmatched for more than
``max_missed`` frames ends. Boxes are ``(x1, y1, x2, y2)`` pixels.

With scores and a ``start_score``, the matching runs twice, as ByteTrack's does (Zhang et al.,
*ByteTrack: Multi-Object Tracking by Associating Every Detection Box*, ECCV 2022): first the
detections scoring at least ``start_score`` against every track, then the lower-scoring ones
against the tracks still unmatched. Only a confident detection starts a track; a doubtful one
continues a track or is dropped. A detector's score falls on a target seen from close by, cut
or blurred, as it does on clutter that looks like the class; the track a confident box started
says which of the two a doubtful box overlapping it is.

Image overlap alone cannot tell two targets apart where one passes in front of the other. A
caller that locates boxes in 3D passes a ``same`` check (``uavcal run``: both located within
``same_radius + target_speed * gap``): a match it refuses is not made (nor a stitch or a re-
acquisition of :mod:`uavcal_jax.track.chain`). On a simulated MH_04 flight a near car drove
across the followed car's box: the far car's box, inside the near one's, was dropped as its
part, and the near car's track took the far car's box when the near one left the image (located
2.3 m apart in one frame); the track chosen was half one car, half the other (filtered RMSE 2.16
m; 0.27 m with the check).

A target seen from close by and steeply above can come out of the detector as a whole box plus
a box of a part of it (a car's bonnet), which NMS keeps: their IoU is small. Such a part would
start a track of its own and could take the followed chain (on a low FLU flight with a 45
degree camera, 18 % of the frames located a part 1-2 m from the car's centre). Before
association, :func:`contained_duplicates` drops a box mostly inside a larger one of the same
class (``merge_contained``, intersection over the smaller box's area), unless the ``same`` check
says it is another target seen past the larger one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["AssociateConfig", "Associator", "box_iou", "contained_duplicates"]


@dataclasses.dataclass(frozen=True)
class AssociateConfig:
    """Settings of the association.

    Attributes:
        min_iou: the least IoU between a track's predicted box and a detection to match them.
        max_missed: frames a track may go unmatched before it ends (predicted meanwhile).
        stitch_gap: the most detected frames between a chain's last box and the box of
            another track that continues it (:mod:`uavcal_jax.track.chain`); longer than
            ``max_missed``: a car at the image's edge can go undetected for a few frames
            while a sliver of it shows, and its next box there overlaps its last one (on a
            simulated V1_02 flight, 8 frames: with 5 the chain ended there, the car 40 % of
            the frames followed and the filtered RMSE 2.09 m; with 15, 56 % and 0.98 m; over
            13 simulated flights 15 changed only one other, indoor_45_13: 1.01 to 0.69 m).
        stitch_iou: the least IoU between a chain's last box and the box that continues it
            (1: never stitch).
        merge_contained: a box whose intersection with a larger box of its class covers at
            least this fraction of its own area is a part of that target and is dropped
            (:func:`contained_duplicates`); ``None``: keep every box.
        reacquire: a chain with no overlapping continuation goes on with the next track of
            its class to appear (:mod:`uavcal_jax.track.chain`; off: its docstring).
        target_speed: m/s, the fastest a target drives (the simulator's car: 6 m/s), and
        same_radius: m, the localisations' error allowed: ``uavcal run`` takes two boxes
            for one target only where they are located within ``same_radius + target_speed
            * gap`` of each other (the module docstring).
    """

    min_iou: float = 0.2
    max_missed: int = 5
    stitch_gap: int = 15
    stitch_iou: float = 0.3
    merge_contained: float | None = 0.6
    reacquire: bool = False
    target_speed: float = 6.0
    same_radius: float = 1.5

    def __post_init__(self):
        if not 0.0 <= self.min_iou < 1.0:
            raise ValueError(f"min_iou must be in [0, 1), got {self.min_iou}")
        if self.max_missed < 0 or self.stitch_gap < 0:
            raise ValueError(f"max_missed and stitch_gap must be >= 0, got {self.max_missed} "
                             f"and {self.stitch_gap}")
        if not 0.0 < self.stitch_iou <= 1.0:
            raise ValueError(f"stitch_iou must be in (0, 1], got {self.stitch_iou}")
        if self.target_speed < 0.0 or self.same_radius < 0.0:
            raise ValueError(f"target_speed and same_radius must be >= 0, got "
                             f"{self.target_speed} and {self.same_radius}")
        if self.merge_contained is not None and not 0.0 < self.merge_contained <= 1.0:
            raise ValueError(f"merge_contained must be in (0, 1] or None, got "
                             f"{self.merge_contained}")


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of boxes ``a`` (N, 4) and ``b`` (M, 4) -> (N, M)."""
    a = np.asarray(a, np.float64).reshape(-1, 4)[:, None, :]
    b = np.asarray(b, np.float64).reshape(-1, 4)[None, :, :]
    inter = _intersection(a, b)
    union = _area(a) + _area(b) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def _area(x: np.ndarray) -> np.ndarray:
    return np.clip(x[..., 2] - x[..., 0], 0, None) * np.clip(x[..., 3] - x[..., 1], 0, None)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection areas of boxes ``a`` and ``b`` (broadcast, ``(..., 4)``)."""
    wh = np.clip(np.minimum(a[..., 2:], b[..., 2:]) - np.maximum(a[..., :2], b[..., :2]), 0, None)
    return wh[..., 0] * wh[..., 1]


def contained_duplicates(boxes: np.ndarray, class_ids: np.ndarray,
                         min_overlap: float | None,
                         same: Callable[[int, int], bool] | None = None) -> np.ndarray:
    """(N,) bool, ``True`` for the boxes to keep: largest first, a box whose intersection with
    a kept larger box of its class covers at least ``min_overlap`` of its own area is dropped
    (``None``: all kept). Boxes ``(N, 4)`` ``x1, y1, x2, y2`` pixels, class ids ``(N,)``.

    ``same(i, j)``: may the larger box ``i`` and the box ``j`` inside it be one target? Where
    not, ``j`` is another target seen past ``i`` and is kept (``None``: never asked)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    class_ids = np.asarray(class_ids, np.int64).reshape(-1)
    keep = np.ones(len(boxes), bool)
    if min_overlap is None or len(boxes) < 2:
        return keep
    area = _area(boxes)
    inter = _intersection(boxes[:, None, :], boxes[None, :, :])
    for i in np.argsort(-area, kind="stable"):
        if not keep[i]:
            continue
        part = (keep & (class_ids == class_ids[i]) & (np.arange(len(boxes)) != i)
                & (area <= area[i]) & (inter[i] >= min_overlap * np.maximum(area, 1e-12)))
        if same is not None:
            part &= np.array([p and same(int(i), j) for j, p in enumerate(part)], bool)
        keep &= ~part
    return keep


@dataclasses.dataclass
class _Track:
    id: int
    class_id: int
    box: np.ndarray  # last matched box
    velocity: np.ndarray  # box change per frame
    last_frame: int
    last_index: int  # the last matched box's index in its frame

    def predicted(self, k: int) -> np.ndarray:
        """(4,) the box expected at frame ``k``: the last one moved at its last velocity."""
        return self.box + (k - self.last_frame) * self.velocity


class Associator:
    """Track ids for the detections of one frame after another: Hungarian
    matching on IoU (its state: the live tracks and the next id); frames are counted by the
    calls to :meth:`step`."""

    def __init__(self, config: AssociateConfig = AssociateConfig()):
        self.config = config
        self.tracks: list[_Track] = []
        self.next_id = 0
        self.frame = -1  # the last frame stepped

    def alive(self, track_id: int) -> bool:
        """Track ``track_id`` may still be matched at the next frame."""
        return any(t.id == track_id for t in self.tracks
                   if self.frame + 1 - t.last_frame <= self.config.max_missed + 1)

    def could_continue(self, frame_boxes: np.ndarray, frame_classes: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the next frame's boxes (N, 4) of classes (N,) overlap a live
        track's predicted box of their class by ``min_iou``: the only boxes a doubtful
        detection (below ``start_score``) can be matched as, so a caller may skip the rest
        before any costly check (:meth:`step` would give them id -1)."""
        frame_boxes = np.asarray(frame_boxes, np.float64).reshape(-1, 4)
        frame_classes = np.asarray(frame_classes, np.int64).reshape(-1)
        k = self.frame + 1
        live = [t for t in self.tracks if k - t.last_frame <= self.config.max_missed + 1]
        if not live or not len(frame_boxes):
            return np.zeros(len(frame_boxes), bool)
        predicted = np.stack([t.predicted(k) for t in live])
        same_class = np.array([t.class_id for t in live])[:, None] == frame_classes[None, :]
        iou = np.where(same_class, box_iou(predicted, frame_boxes), 0.0)
        return iou.max(axis=0) >= max(self.config.min_iou, 1e-12)

    def step(self, frame_boxes: np.ndarray, frame_classes: np.ndarray,
             same: Callable[[int, int, int, int], bool] | None = None,
             scores: np.ndarray | None = None, start_score: float = 0.0) -> np.ndarray:
        """(N,) track ids (0, 1, 2, ... in order of first appearance) of the next frame's
        boxes (N, 4) of classes (N,); -1 for a box scoring below ``start_score`` that
        continues no track (the module docstring; ``scores`` (N,) ``None``: every box may
        start one). ``same(k_last, i_last, k, i)``: may box ``i`` of frame ``k`` be the target
        of a track whose last box was ``i_last`` of frame ``k_last``? Asked of the pairs that
        overlap enough to match; a pair it refuses is not matched (``None``: yes)."""
        config = self.config
        k = self.frame = self.frame + 1
        frame_boxes = np.asarray(frame_boxes, np.float64).reshape(-1, 4)
        frame_classes = np.asarray(frame_classes, np.int64).reshape(-1)
        confident = (np.ones(len(frame_boxes), bool) if scores is None
                     else np.asarray(scores, np.float64).reshape(-1) >= start_score)
        self.tracks = [t for t in self.tracks if k - t.last_frame <= config.max_missed + 1]
        ids = np.full(len(frame_boxes), -1, np.int64)
        matched = self._match(k, frame_boxes, frame_classes, confident, self.tracks, same, ids)
        self._match(k, frame_boxes, frame_classes, ~confident,
                    [t for t in self.tracks if t.id not in matched], same, ids)
        for c in np.flatnonzero((ids < 0) & confident):
            self.tracks.append(_Track(self.next_id, int(frame_classes[c]), frame_boxes[c],
                                      np.zeros(4), k, int(c)))
            ids[c] = self.next_id
            self.next_id += 1
        return ids

    def _match(self, k: int, frame_boxes: np.ndarray, frame_classes: np.ndarray,
               usable: np.ndarray, tracks: list[_Track], same, ids: np.ndarray) -> set[int]:
        """Frame ``k``'s ``usable`` boxes matched to ``tracks`` (Hungarian on IoU): the tracks
        updated and their ids written into ``ids``; returns the ids of the tracks matched."""
        min_iou = max(self.config.min_iou, 1e-12)
        if not tracks or not usable.any():
            return set()
        predicted = np.stack([t.predicted(k) for t in tracks])
        iou = box_iou(predicted, frame_boxes)
        same_class = np.array([t.class_id for t in tracks])[:, None] == frame_classes[None, :]
        iou = np.where(same_class & usable[None, :], iou, 0.0)
        if same is not None:
            for r, c in zip(*np.nonzero(iou >= min_iou), strict=True):
                if not same(tracks[r].last_frame, tracks[r].last_index, k, int(c)):
                    iou[r, c] = 0.0
        matched = set()
        rows, cols = linear_sum_assignment(-iou)
        for r, c in zip(rows, cols, strict=True):
            if iou[r, c] < min_iou:
                continue
            track = tracks[r]
            track.velocity = (frame_boxes[c] - track.box) / (k - track.last_frame)
            track.box, track.last_frame, track.last_index = frame_boxes[c], k, int(c)
            ids[c] = track.id
            matched.add(track.id)
        return matched
