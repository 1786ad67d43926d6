"""Frame-to-frame association of detections into tracks, and the choice of the target to follow.

Plain NumPy (detections vary in number per frame). Each track predicts its box one frame on
with the box's last velocity (constant velocity in the image, so two targets crossing keep
their ids); detections are matched to the predictions of the same class by the Hungarian
assignment on IoU (``scipy.optimize.linear_sum_assignment``), pairs below ``min_iou`` are not
matched. Unmatched detections start new tracks; a track unmatched for more than
``max_missed`` frames ends. Boxes are ``(x1, y1, x2, y2)`` pixels.

Image overlap alone cannot tell two targets apart where one passes in front of the other. A
caller that locates boxes in 3D passes a ``same`` check (``uavcal run``: both located within
``same_radius + target_speed * gap``): a match, a stitch and a re-acquisition it refuses are
not made. On a simulated MH_04 flight a near car drove across the followed car's box: the far
car's box, inside the near one's, was dropped as its part, and the near car's track took the
far car's box when the near one left the image (located 2.3 m apart in one frame); the track
chosen was half one car, half the other (filtered RMSE 2.16 m; 0.27 m with the check).

The target followed is a chain of tracks (:func:`followed_detections`): a track's identity breaks
where the detector merges two overlapping targets into one box and splits them again (on a
simulated V2_02 flight a passing car took the followed car's box for 0.2 s, and its track ended
with the car in full view for 1.5 s more). The chain goes on with the track of the same class whose
box, within ``stitch_gap`` detected frames after the chain's last one, overlaps that last box by
``stitch_iou`` (and backwards the same way); a track boxed beside the chain's last box, in the same
frame, is another target and is never taken. Where no box overlaps, the target has left the image
or was hidden for longer, and a follower re-acquires it when it shows again (as the closed loop's
chooser does): with ``reacquire`` the chain goes on with the next track of its class to appear (the
longest of those starting first; backwards, of those ending last), if the caller's ``same`` check
agrees (``uavcal run`` locates both boxes and asks that the target could have driven between them).
It is off by default: on a simulated V2_03 flight the car, hidden 1 s behind a person, came back as
a new track that the chain otherwise misses for the flight's last 6.4 s (filtered RMSE 0.66 m
without, 0.54 m with), but the segments it adds are the hard ones (a car cut by the border, seen
end-on, just re-found): over nine simulated flights it raised the filtered median on three (V2_03
0.35 to 0.38 m, V2_02 0.28 to 0.31 m, a forward UZH-FPV flight 0.98 to 1.15 m) and the RMSE on
three (V2_02 0.79 to 0.83 m, indoor_45_12 0.37 to 0.77 m, the forward flight 1.68 to 2.00 m), and
changed none of the others.

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
from collections.abc import Callable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["AssociateConfig", "assign_track_ids", "box_iou", "contained_duplicates",
           "followed_detections", "longest_track"]


@dataclasses.dataclass(frozen=True)
class AssociateConfig:
    """Settings of the association.

    Attributes:
        min_iou: the least IoU between a track's predicted box and a detection to match them.
        max_missed: frames a track may go unmatched before it ends (predicted meanwhile).
        stitch_gap: the most detected frames between a chain's last box and the box of
            another track that continues it (:func:`followed_detections`); longer than
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
            its class to appear (:func:`followed_detections`; off: the module docstring).
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


def assign_track_ids(boxes: Sequence[np.ndarray], class_ids: Sequence[np.ndarray],
                     config: AssociateConfig = AssociateConfig(),
                     same: Callable[[int, int, int, int], bool] | None = None
                     ) -> list[np.ndarray]:
    """Track ids for every detection of every frame.

    Args:
        boxes: per frame, (N_k, 4) detected boxes.
        class_ids: per frame, (N_k,) their class ids.
        config: :class:`AssociateConfig`.
        same: ``same(k_last, i_last, k, i)``: may box ``i`` of frame ``k`` be the target of
            a track whose last box was ``i_last`` of frame ``k_last``? Asked of the pairs that
            overlap enough to match; a pair it refuses is not matched (``None``: yes).

    Returns:
        per frame, (N_k,) int track ids (0, 1, 2, ... in order of first appearance).
    """
    if len(boxes) != len(class_ids):
        raise ValueError(f"{len(boxes)} frames of boxes but {len(class_ids)} of class ids")
    tracks: list[_Track] = []
    next_id = 0
    out = []
    for k, (frame_boxes, frame_classes) in enumerate(zip(boxes, class_ids, strict=True)):
        frame_boxes = np.asarray(frame_boxes, np.float64).reshape(-1, 4)
        frame_classes = np.asarray(frame_classes, np.int64).reshape(-1)
        tracks = [t for t in tracks if k - t.last_frame <= config.max_missed + 1]
        ids = np.full(len(frame_boxes), -1, np.int64)
        if tracks and len(frame_boxes):
            predicted = np.stack([t.box + (k - t.last_frame) * t.velocity for t in tracks])
            iou = box_iou(predicted, frame_boxes)
            same_class = (np.array([t.class_id for t in tracks])[:, None]
                          == frame_classes[None, :])
            iou = np.where(same_class, iou, 0.0)
            if same is not None:
                for r, c in zip(*np.nonzero(iou >= max(config.min_iou, 1e-12)), strict=True):
                    if not same(tracks[r].last_frame, tracks[r].last_index, k, int(c)):
                        iou[r, c] = 0.0
            rows, cols = linear_sum_assignment(-iou)
            for r, c in zip(rows, cols, strict=True):
                if iou[r, c] < max(config.min_iou, 1e-12):
                    continue
                track = tracks[r]
                gap = k - track.last_frame
                track.velocity = (frame_boxes[c] - track.box) / gap
                track.box, track.last_frame, track.last_index = frame_boxes[c], k, int(c)
                ids[c] = track.id
        for c in np.flatnonzero(ids < 0):
            tracks.append(_Track(next_id, int(frame_classes[c]), frame_boxes[c], np.zeros(4), k,
                                 int(c)))
            ids[c] = next_id
            next_id += 1
        out.append(ids)
    return out


def longest_track(track_ids: Sequence[np.ndarray], class_ids: Sequence[np.ndarray],
                  class_id: int, usable: Sequence[np.ndarray] | None = None) -> int | None:
    """The id of the longest track (most frames) of class ``class_id``; ties go to the
    earliest track; ``None`` when there is none.

    ``usable``: per frame, a bool mask over its detections; only usable detections count
    (a follower wants the target it can locate most often, not a box that stays cut by the
    image border all flight)."""
    ids = np.concatenate([np.asarray(t, np.int64).reshape(-1) for t in track_ids] or [[]])
    classes = np.concatenate([np.asarray(c, np.int64).reshape(-1) for c in class_ids] or [[]])
    keep = classes == class_id
    if usable is not None:
        keep &= np.concatenate([np.asarray(u, bool).reshape(-1) for u in usable] or [[]])
    ids = ids[keep].astype(np.int64)
    if ids.size == 0:
        return None
    counts = np.bincount(ids)
    return int(np.argmax(counts))


def followed_detections(track_ids: Sequence[np.ndarray], boxes: Sequence[np.ndarray],
                        class_ids: Sequence[np.ndarray], chosen: int,
                        config: AssociateConfig = AssociateConfig(),
                        same: Callable[[int, int, int, int], bool] | None = None
                        ) -> np.ndarray:
    """Per frame, the index of the followed target's detection (``-1``: none): track
    ``chosen`` (e.g. :func:`longest_track`), continued forwards and backwards by other tracks
    of its class (the module docstring).

    Args:
        track_ids: per frame, (N_k,) track ids (:func:`assign_track_ids`).
        boxes: per frame, (N_k, 4) the detections' boxes.
        class_ids: per frame, (N_k,) their class ids.
        chosen: the track the chain starts from.
        config: :class:`AssociateConfig` (``stitch_gap``, ``stitch_iou``, ``reacquire``).
        same: ``same(k_end, i_end, k, i)``: may detection ``i`` of frame ``k`` be
            the target whose last detection was ``i_end`` of frame ``k_end``? Asked before
            stitching and re-acquiring (``None``: yes).

    Returns:
        (T,) int detection indices.
    """
    T = len(track_ids)
    pick = np.full(T, -1, np.int64)
    ids = [np.asarray(t, np.int64).reshape(-1) for t in track_ids]
    boxes = [np.asarray(b, np.float64).reshape(-1, 4) for b in boxes]
    classes = [np.asarray(c, np.int64).reshape(-1) for c in class_ids]
    frames = [k for k in range(T) if np.any(ids[k] == chosen)]
    if not frames:
        return pick
    class_id = int(classes[frames[0]][np.flatnonzero(ids[frames[0]] == chosen)[0]])
    used = {chosen}

    def take(track: int, ks) -> int | None:
        """Mark ``track``'s detections over frames ``ks`` (in order, while unmarked); the
        last frame marked."""
        last = None
        for k in ks:
            hit = np.flatnonzero(ids[k] == track)
            if hit.size and pick[k] < 0:
                pick[k], last = hit[0], k
        return last

    take(chosen, frames)
    for step in (1, -1):
        end = frames[-1] if step > 0 else frames[0]
        while end is not None:
            ref = boxes[end][pick[end]][None]
            found = None
            for k in range(end + step, end + step * (config.stitch_gap + 2), step):
                if not 0 <= k < T:
                    break
                # a track boxed beside the chain's last box is another target
                candidate = (classes[k] == class_id) & ~np.isin(ids[k], [*used, *ids[end]])
                if not candidate.any():
                    continue
                iou = np.where(candidate, box_iou(ref, boxes[k])[0], 0.0)
                for i in np.argsort(-iou, kind="stable"):
                    if iou[i] < config.stitch_iou:
                        break
                    if same is None or same(end, int(pick[end]), k, int(i)):
                        found = (k, int(ids[k][i]))
                        break
                if found is not None:
                    break
            if found is None and config.reacquire:
                found = _next_track(ids, classes, class_id, used, end, step, same, pick)
            if found is None:
                break
            k, track = found
            used.add(track)
            later = range(k, T) if step > 0 else range(k, -1, -1)
            end = take(track, later)
    return pick


def _next_track(ids, classes, class_id: int, used: set, end: int, step: int, same,
                pick) -> tuple[int, int] | None:
    """The first track of class ``class_id`` (not in ``used``) to appear after frame ``end``
    going ``step`` (+1 forwards: its first frame is after ``end``; -1 backwards: its last is
    before) that ``same`` accepts, the longest of those appearing together: ``(frame,
    track)``, or ``None``. A track seen at ``end`` too is another target, never taken."""
    seen: dict[int, list[int]] = {}
    for k, (frame_ids, frame_classes) in enumerate(zip(ids, classes, strict=True)):
        for t in frame_ids[(frame_classes == class_id) & (frame_ids >= 0)]:
            seen.setdefault(int(t), []).append(k)
    starts: dict[int, list[int]] = {}  # frame -> the tracks appearing there
    for t, ks in seen.items():
        first = ks[0] if step > 0 else ks[-1]
        if t not in used and (first - end) * step > 0:
            starts.setdefault(first, []).append(t)
    for k in sorted(starts, key=lambda f: (f - end) * step):
        for track in sorted(starts[k], key=lambda t: -len(seen[t])):
            i = int(np.flatnonzero(ids[k] == track)[0])
            if same is None or same(end, int(pick[end]), k, i):
                return k, track
    return None
