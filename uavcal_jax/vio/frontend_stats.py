"""What the VIO's front end sees in a stereo sequence: corners, track survival, LK residuals
and stereo inliers (``experiments/sim_realism.py`` compares them on real and rendered frames).

Every figure comes from the VIO's own :class:`~uavcal_jax.vio.frontend.FeatureTracker`: its
equalisation, its Shi-Tomasi and Lucas-Kanade settings (:class:`~uavcal_jax.vio.config.
FrontendConfig`) and, for survival and stereo, its whole ``track`` step (forward-backward
check, outlier rejection, stereo epipolar and cheirality checks), so that a difference between
real and rendered frames is one the VIO feels. Images are (H, W) uint8 gray; pixels follow
OpenCV's convention (integer values at pixel centres).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from uavcal_jax.vio.frontend import FeatureTracker
from uavcal_jax.vio.match_checks import stereo_epipolar_distance, stereo_in_front

__all__ = ["STEREO_STATUS", "corner_count", "lk_pair_stats", "stereo_matches", "tracking_stats"]

#: :func:`stereo_matches`' status codes, in order: matched; LK found no match; the match
#: failed the forward-backward check; it failed the epipolar or cheirality check.
STEREO_STATUS = ("matched", "not found", "forward-backward", "epipolar")


def corner_count(tracker: FeatureTracker, image: np.ndarray) -> int:
    """Shi-Tomasi corners (``goodFeaturesToTrack`` with the tracker's quality level, minimum
    distance and block size, on its equalised image) in one (H, W) image, without the
    tracker's ``max_features`` cap: how much trackable texture the image has."""
    cfg = tracker.config
    corners = cv2.goodFeaturesToTrack(tracker.equalised(image), 0, cfg.quality_level,
                                      cfg.min_distance_px, blockSize=cfg.block_size)
    return 0 if corners is None else len(corners)


def _lk_both_ways(tracker: FeatureTracker, image0: np.ndarray, image1: np.ndarray):
    """The tracker's ``max_features`` strongest corners of ``image0`` tracked into ``image1``
    by LK (its window, pyramid and criteria; from scratch) and back.

    Returns:
        ``None`` where ``image0`` has no corner; else ``(pts0 (N, 2), pts1 (N, 2), err (N,),
        found (N,) bool, fb (N,))``: the corners, where they landed, OpenCV's LK error (mean
        absolute window difference, grey levels), found both ways, and the forward-backward
        distance (pixels).
    """
    cfg = tracker.config
    img0, img1 = tracker.equalised(image0), tracker.equalised(image1)
    pts0 = cv2.goodFeaturesToTrack(img0, cfg.max_features, cfg.quality_level,
                                   cfg.min_distance_px, blockSize=cfg.block_size)
    if pts0 is None:
        return None
    pts0 = pts0.astype(np.float32)
    lk = tracker.lk_params
    pts1, st, err = cv2.calcOpticalFlowPyrLK(img0, img1, pts0, None, maxLevel=cfg.lk_max_level,
                                             **lk)
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(img1, img0, pts1, None, maxLevel=cfg.lk_max_level,
                                             **lk)
    pts0, pts1 = pts0.reshape(-1, 2), pts1.reshape(-1, 2)
    found = (st.reshape(-1) == 1) & (st_b.reshape(-1) == 1)
    fb = np.linalg.norm(back.reshape(-1, 2) - pts0, axis=1)
    return pts0, pts1, err.reshape(-1), found, fb


def lk_pair_stats(tracker: FeatureTracker, image0: np.ndarray, image1: np.ndarray
                  ) -> dict[str, float]:
    """Lucas-Kanade from ``image0`` to ``image1`` ((H, W) each) of the tracker's
    ``max_features`` strongest corners of ``image0``, with its window, pyramid and stopping
    criteria, and the backward check.

    Returns:
        ``survival``: the fraction of corners found forward and backward that return within
        ``fb_threshold_px`` of their start; ``residual``: the median of OpenCV's LK error over
        them (the mean absolute difference of the equalised window, grey levels);
        ``fb_px``: their median forward-backward distance, pixels; ``corners``: how many
        corners were tracked. NaN figures when ``image0`` has no corner.
    """
    flow = _lk_both_ways(tracker, image0, image1)
    if flow is None:
        return {"survival": float("nan"), "residual": float("nan"), "fb_px": float("nan"),
                "corners": 0}
    pts0, _, err, found, fb = flow
    ok = found & (fb <= tracker.config.fb_threshold_px)
    return {"survival": float(ok.mean()),
            "residual": float(np.median(err[found])) if found.any() else float("nan"),
            "fb_px": float(np.median(fb[found])) if found.any() else float("nan"),
            "corners": len(pts0)}


def stereo_matches(tracker: FeatureTracker, left: np.ndarray, right: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Why each of a left image's corners does or does not find its right match.

    The tracker's ``max_features`` strongest corners of ``left`` ((H, W) uint8) are tracked
    into ``right`` with its LK settings from scratch (no disparity seed), then checked as its
    ``track`` step checks them (forward-backward distance, epipolar distance, in front of both
    cameras).

    Returns:
        ``(pts (N, 2) float32 left pixels, status (N,) int8)``: an index into
        :data:`STEREO_STATUS` per corner (the first check it fails).
    """
    flow = _lk_both_ways(tracker, left, right)
    if flow is None:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.int8)
    pts0, pts1, _, found, fb = flow
    cfg = tracker.config
    back_ok = found & (fb <= cfg.fb_threshold_px)
    xy, xy_r = tracker.normalised(pts0), tracker.normalised(pts1, right=True)
    tol = cfg.stereo_epipolar_px / float(tracker.K0[0, 0])
    geometric = (stereo_epipolar_distance(xy, xy_r, tracker.T_C0C1) <= tol) & stereo_in_front(
        xy, xy_r, tracker.T_C0C1, tol)
    status = np.full(len(pts0), 3, np.int8)
    status[back_ok & geometric] = 0
    status[~found] = 1
    status[found & ~back_ok] = 2
    return pts0, status


def tracking_stats(tracker: FeatureTracker, left: Sequence[np.ndarray],
                   right: Sequence[np.ndarray] | None = None,
                   times: Sequence[float] | None = None) -> dict[str, float]:
    """Run the tracker (reset first) over a stereo sequence and summarise what it kept.

    Args:
        tracker: the VIO's tracker for the sequence's cameras.
        left: (H, W) uint8 left images, in time order.
        right: the right images (same count), or ``None``.
        times: frame times, seconds (default 0.05 s apart: only the order matters here).

    Returns:
        ``survival``: the mean over consecutive frames of the fraction of one frame's features
        still tracked in the next (ids kept through the forward-backward check and the
        outlier rejection); ``stereo_rate``: the mean fraction of a frame's features with an
        accepted right match; ``tracked``: the mean features per frame.
    """
    if right is not None and len(right) != len(left):
        raise ValueError(f"{len(left)} left and {len(right)} right images")
    times = np.arange(len(left)) * 0.05 if times is None else np.asarray(times, np.float64)
    tracker.reset()
    survival, stereo, tracked = [], [], []
    prev_ids = None
    for k, img in enumerate(left):
        f = tracker.track(float(times[k]), img, None if right is None else right[k])
        ids = f.ids[f.mask]
        if prev_ids is not None and len(prev_ids):
            survival.append(np.isin(prev_ids, ids).mean())
        if f.n_tracked:
            stereo.append(f.n_stereo / f.n_tracked)
        tracked.append(f.n_tracked)
        prev_ids = ids
    return {"survival": float(np.mean(survival)) if survival else float("nan"),
            "stereo_rate": float(np.mean(stereo)) if stereo else float("nan"),
            "tracked": float(np.mean(tracked))}
