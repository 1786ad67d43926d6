"""The target to follow, chosen frame by frame as a live follower must (causal), over the
track ids of :class:`~uavcal_jax.track.associate.Associator`:

* while a track is followed and has a box in the frame, that box is the target;
* while it has none, within ``stitch_gap`` frames after its last box, the chain goes on with
  another track of the class whose box overlaps that last box by ``stitch_iou``, if the
  caller's ``same`` check agrees; a track boxed beside the last box, in the same frame, is
  another target and is never taken. A track's identity breaks where the detector merges two
  overlapping targets into one box and splits them again (on a simulated V2_02 flight a
  passing car took the followed car's box for 0.2 s, and its track ended with the car in full
  view for 1.5 s more);
* with ``reacquire``, also with a track of the class that appears (its first box) after the
  chain's last box, the longest of those appearing together, if ``same`` agrees (``uavcal
  run`` locates both boxes and asks that the target could have driven between them). It is off
  by default: with the offline chain this module replaced (which also ran backwards from the
  flight's longest track), over nine simulated flights it raised the filtered median on three
  (V2_03 0.35 to 0.38 m, V2_02 0.28 to 0.31 m, a forward UZH-FPV flight 0.98 to 1.15 m) and
  the RMSE on three (V2_02 0.79 to 0.83 m, indoor_45_12 0.37 to 0.77 m, the forward flight
  1.68 to 2.00 m): the segments it adds are the hard ones (a car cut by the border, seen
  end-on, just re-found);
* with no target followed, or the chain lost (``stitch_gap`` frames without its box), the
  target is the track of the class present in the frame with the most boxes inside the image
  so far (a box cut by the border cannot be located), ties to the earliest track: the longest
  track, as far as it is known yet. A chain is never switched away from while its target is
  seen.

Plain Python/NumPy; boxes ``(x1, y1, x2, y2)`` pixels; frames counted as the
:class:`~uavcal_jax.track.associate.Associator` counts them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from uavcal_jax.track.associate import AssociateConfig, box_iou

__all__ = ["FollowedChain"]


class FollowedChain:
    """The followed target's detection, frame after frame (the module docstring).

    State: ``track`` (the track followed, ``None`` before any), the chain's last box (its
    frame ``end``, index, box and the ids beside it), the tracks it has used, and per track
    of the class its boxes inside the image so far and its first frame."""

    def __init__(self, class_id: int, config: AssociateConfig):
        self.class_id, self.config = class_id, config
        self.track: int | None = None
        self.end, self.end_index = -1, -1
        self.end_box, self.end_ids = np.full(4, np.nan), np.zeros(0, np.int64)
        self.used: set[int] = set()
        self.usable: dict[int, int] = {}
        self.seen: dict[int, int] = {}
        self.first: dict[int, int] = {}

    def step(self, k: int, ids: np.ndarray, boxes: np.ndarray, classes: np.ndarray,
             inside: np.ndarray, same: Callable[[int, int, int, int], bool] | None = None
             ) -> int:
        """The index of the followed target's box in frame ``k`` (``-1``: none).

        Args:
            k: the frame (increasing).
            ids, boxes, classes: the frame's (N,) track ids, (N, 4) boxes, (N,) class ids.
            inside: (N,) bool, a box can be located (not cut by the image border).
            same: ``same(k_end, i_end, k, i)``: may box ``i`` of frame ``k`` be the target
                whose last box was ``i_end`` of frame ``k_end``? (``None``: yes.)
        """
        ids = np.asarray(ids, np.int64).reshape(-1)
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        mine = np.asarray(classes, np.int64).reshape(-1) == self.class_id
        for t, ok in zip(ids[mine], np.asarray(inside, bool).reshape(-1)[mine], strict=True):
            t = int(t)
            self.usable[t] = self.usable.get(t, 0) + int(ok)
            self.seen[t] = self.seen.get(t, 0) + 1
            self.first.setdefault(t, k)
        pick = self._continue(k, ids, boxes, mine, same)
        if pick < 0 and (self.track is None or k - self.end > self.config.stitch_gap + 1):
            pick = self._choose(ids, mine)
            if pick >= 0:
                self.used = set()
        if pick >= 0:
            self.track = int(ids[pick])
            self.used.add(self.track)
            self.end, self.end_index, self.end_box, self.end_ids = k, pick, boxes[pick], ids
        return pick

    def _continue(self, k, ids, boxes, mine, same) -> int:
        """The followed track's box, else a stitch or a re-acquisition (``-1``: none)."""
        if self.track is None:
            return -1
        hit = np.flatnonzero(ids == self.track)
        if hit.size:
            return int(hit[0])

        def agrees(i) -> bool:
            return same is None or same(self.end, self.end_index, k, int(i))

        candidate = mine & ~np.isin(ids, [*self.used, *self.end_ids])
        if candidate.any() and k - self.end <= self.config.stitch_gap + 1:
            iou = np.where(candidate, box_iou(self.end_box[None], boxes)[0], 0.0)
            for i in np.argsort(-iou, kind="stable"):
                if iou[i] < self.config.stitch_iou:
                    break
                if agrees(i):
                    return int(i)
        if self.config.reacquire:
            new = [int(i) for i in np.flatnonzero(candidate) if self.first[int(ids[i])] == k]
            for i in sorted(new, key=lambda i: -self.seen[int(ids[i])]):
                if agrees(i):
                    return i
        return -1

    def _choose(self, ids, mine) -> int:
        """The box of the present track of the class with the most boxes inside the image so
        far (then the most boxes, then the earliest); ``-1`` without one."""
        present = np.flatnonzero(mine)
        if not present.size:
            return -1
        keys = [(self.usable[int(ids[i])], self.seen[int(ids[i])], -int(ids[i]))
                for i in present]
        return int(present[max(range(len(keys)), key=keys.__getitem__)])
