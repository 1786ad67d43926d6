"""The host's bookkeeping of one sliding window, from the frame that opens it to its reset:
which keyframe slot holds which frame, which landmark slot which tracked corner, which slots
are free, and the window's keyframe reference and counters.

The device arrays (:class:`~uavcal_jax.vio.window.WindowState`,
:class:`~uavcal_jax.vio.window.WindowProblem`) are the truth; this is their mirror, refreshed
from :func:`~uavcal_jax.vio.window_ops.window_summary` after every edit that can free slots
(a solve's prune, a slide), so that the next frame's measurements can be packed without
reading the window back.

Slots: keyframe slots ``0 .. newest`` are in use, contiguously, oldest first; landmark slots
and observation slots are used in any order (``landmark_used``, ``observation_used``).
"""

from __future__ import annotations

import jax
import numpy as np

from uavcal_jax.vio.frontend import FrameFeatures
from uavcal_jax.vio.initialize import triangulate_stereo
from uavcal_jax.vio.window import WindowProblem
from uavcal_jax.vio.window_ops import window_summary

__all__ = ["WindowSlots", "stereo_depths"]


def stereo_depths(feats: FrameFeatures, T_C0C1: np.ndarray, min_depth: float,
                  max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """``(depth (K,) m, usable (K,) bool)`` of each corner's stereo triangulation (NaN without
    a stereo match; usable within ``[min_depth, max_depth]``). ``T_C0C1`` (4, 4): the right
    camera in the left camera's frame."""
    depth = np.full(len(feats.mask), np.nan)
    st = feats.stereo_mask
    if st.any():
        depth[st] = triangulate_stereo(feats.xy[st], feats.xy_right[st], T_C0C1)
    return depth, (depth >= min_depth) & (depth <= max_depth)


class WindowSlots:
    """Host mirror of one window (see the module docstring).

    Args:
        landmarks, observations: the window's capacities ``L`` and ``M``.

    Attributes:
        times: frame time (ns) of each keyframe slot in use.
        keyframe: whether each slot in use holds a keyframe (the newest non-keyframe is
            dropped at the next slide).
        landmark_of: front-end feature id -> landmark slot, for the landmarks alive.
        landmark_used: (L,) bool.  observation_used: (M,) bool.
        rows: residual rows in use at the last summary.
        kf_features: the last keyframe's :class:`FrameFeatures`.  kf_rotation: (3, 3) its
            body-to-world rotation (the keyframe decision's reference).
        filled_once: the window has been full (the gyro bias was refined from its rotations).
    """

    def __init__(self, landmarks: int, observations: int):
        self.times: list[int] = []
        self.keyframe: list[bool] = []
        self.landmark_of: dict[int, int] = {}
        self.landmark_used = np.zeros(landmarks, bool)
        self.observation_used = np.zeros(observations, bool)
        self.rows = 0
        self.kf_features: FrameFeatures | None = None
        self.kf_rotation: np.ndarray | None = None
        self.filled_once = False

    @property
    def newest(self) -> int:
        """Index of the newest slot in use (-1: the window is empty)."""
        return len(self.times) - 1

    def append(self, t_ns: int, is_keyframe: bool) -> None:
        """The frame at ``t_ns`` took slot :attr:`newest` ``+ 1``."""
        self.times.append(t_ns)
        self.keyframe.append(is_keyframe)

    def remove(self, slot: int) -> None:
        """Slot ``slot`` left the window; the later ones moved down by one."""
        del self.times[slot], self.keyframe[slot]

    def last_keyframe_time(self) -> int:
        """ns, frame time of the newest keyframe slot."""
        return self.times[max(i for i, kf in enumerate(self.keyframe) if kf)]

    def mirror(self, problem: WindowProblem) -> int:
        """Read the device's landmark and observation masks back; forget dead landmarks.
        Returns the number of active landmarks."""
        return self.apply_summary(jax.device_get(window_summary(problem)))

    def apply_summary(self, s: dict) -> int:
        """:meth:`mirror` from a :func:`window_summary` already on the host."""
        self.landmark_used = np.array(s["landmark_mask"])
        self.observation_used = np.array(s["observation_mask"])
        self.landmark_of = {i: l for i, l in self.landmark_of.items() if self.landmark_used[l]}
        self.rows = int(s["rows"])
        return int(s["active_landmarks"])

    def measurements(self, feats: FrameFeatures, depth: np.ndarray, usable: np.ndarray,
                     max_features: int) -> tuple[np.ndarray, ...]:
        """Padded updates for :func:`~uavcal_jax.vio.window_ops.insert_frame`, slots taken:
        observations of the corners whose landmark is alive, a new landmark for every other
        stereo match with a usable depth (:func:`stereo_depths`). ``max_features`` ``K`` pads
        the landmark rows (K) and the observation rows (2K); padding points at the capacity
        (dropped). Corners beyond the free slots are skipped."""
        K = max_features
        L, M = len(self.landmark_used), len(self.observation_used)
        lm_slot = np.full(K, L, np.int32)
        lm_bearing = np.zeros((K, 2))
        lm_inv = np.ones(K)
        o_slot = np.full(2 * K, M, np.int32)
        o_lm = np.zeros(2 * K, np.int32)
        o_cam = np.zeros(2 * K, np.int32)
        o_xy = np.zeros((2 * K, 2))
        stereo = feats.stereo_mask
        free_lm = iter(np.flatnonzero(~self.landmark_used))
        free_obs = np.flatnonzero(~self.observation_used)
        n_lm = n_obs = 0
        entries = []  # (landmark slot, camera, xy)
        for i in np.flatnonzero(feats.mask):
            fid = int(feats.ids[i])
            lid = self.landmark_of.get(fid)
            if lid is None:
                if not (stereo[i] and usable[i]):
                    continue
                lid = next(free_lm, None)
                if lid is None:
                    continue
                self.landmark_of[fid] = lid
                self.landmark_used[lid] = True
                lm_slot[n_lm], lm_bearing[n_lm], lm_inv[n_lm] = lid, feats.xy[i], 1.0 / depth[i]
                n_lm += 1
                entries.append((lid, 1, feats.xy_right[i]))
                continue
            entries.append((lid, 0, feats.xy[i]))
            if stereo[i]:
                entries.append((lid, 1, feats.xy_right[i]))
        for lid, cam, xy in entries[:len(free_obs)]:
            o_slot[n_obs], o_lm[n_obs], o_cam[n_obs], o_xy[n_obs] = free_obs[n_obs], lid, cam, xy
            n_obs += 1
        self.observation_used[o_slot[:n_obs]] = True
        return lm_slot, lm_bearing, lm_inv, o_slot, o_lm, o_cam, o_xy
