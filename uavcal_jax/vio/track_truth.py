"""Score the front end's matches against a simulated recording's ground truth.

A simulated sequence (:mod:`uavcal_jax.sim`) carries the true body poses and, per frame, the
rendered z-depth of the left camera (``depth0``, metres). That fixes where every tracked
corner truly is: a left observation ``uv`` at frame ``k`` back-projects with the depth under
it and the true pose ``T_WC0(k)`` to a world point, which projects into any other frame and
into the right camera. :func:`match_truth` measures, per frame:

* **temporal** errors: a corner tracked from frame ``k - 1`` against where its ``k - 1``
  observation truly moves to in frame ``k`` (the optical flow's error, one frame);
* **drift**: the same against the track's *first* observation (the error accumulated along
  the track, the one the window's landmark sees);
* **stereo** errors: a right observation against the true projection of its left one;
* **depth** errors: the stereo triangulation's depth against the rendered one.

Conventions are the front end's (:mod:`uavcal_jax.vio.frontend`): pixels with integer values at
pixel centres (the simulator renders at pixel centres, depth and labels at the frame's
mid-exposure pose), radial-tangential distortion through OpenCV. A corner whose 3 x 3 depth
neighbourhood spans more than ``edge_rel`` of its depth sits on an occluding edge, where the
back-projection is ambiguous: it is not scored. Pure NumPy/OpenCV, float64; a diagnostic, not
part of the estimator.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from uavcal_jax.data.sequence import CameraCalibration, GroundTruth
from uavcal_jax.errors import DataError
from uavcal_jax.vio.frontend import FrameFeatures

__all__ = ["MatchTruth", "body_poses_at", "match_truth"]

#: Default error (pixels) above which a match counts as wrong.
WRONG_PX = 2.0


@dataclasses.dataclass(frozen=True)
class MatchTruth:
    """Per-frame scores of :func:`match_truth` (arrays of length F, one per frame).

    Attributes:
        t_ns: (F,) frame times.
        temporal_n, temporal_bad: corners tracked from the previous frame that could be scored,
            and those whose position is off by more than the threshold (pixels).
        temporal_median_px: median temporal error (``nan`` with none scored).
        drift_n, drift_bad, drift_median_px: the same against each track's first observation.
        stereo_n, stereo_bad, stereo_median_px: the same for the right observations.
        depth_median_rel: median of ``|stereo depth / true depth - 1|`` over the stereo matches.
        true_flow_median_px: median true displacement of the scored corners since the previous
            frame, pixels (how far the flow had to reach).
        true_depth_median_m: median rendered depth of the frame's corners, metres.
    """

    t_ns: np.ndarray
    temporal_n: np.ndarray
    temporal_bad: np.ndarray
    temporal_median_px: np.ndarray
    drift_n: np.ndarray
    drift_bad: np.ndarray
    drift_median_px: np.ndarray
    stereo_n: np.ndarray
    stereo_bad: np.ndarray
    stereo_median_px: np.ndarray
    depth_median_rel: np.ndarray
    true_flow_median_px: np.ndarray
    true_depth_median_m: np.ndarray

    def fraction(self, kind: str) -> np.ndarray:
        """(F,) the share of ``kind`` (``"temporal"``, ``"drift"`` or ``"stereo"``) matches off
        by more than the threshold (``nan`` where none was scored)."""
        n = getattr(self, f"{kind}_n").astype(np.float64)
        bad = getattr(self, f"{kind}_bad")
        return np.where(n > 0, bad / np.maximum(n, 1), np.nan)

    def summary(self) -> dict:
        """JSON-ready means over the frames: wrong shares, median errors, flow and depth."""
        out = {}
        for kind in ("temporal", "drift", "stereo"):
            n = getattr(self, f"{kind}_n")
            out[f"{kind}_wrong_share"] = (float(getattr(self, f"{kind}_bad").sum() / n.sum())
                                          if n.sum() else float("nan"))
            out[f"{kind}_wrong_share_worst_frame"] = float(np.nanmax(self.fraction(kind))) \
                if np.any(n > 0) else float("nan")
            out[f"{kind}_median_px"] = float(np.nanmedian(getattr(self, f"{kind}_median_px"))) \
                if np.any(n > 0) else float("nan")
            out[f"{kind}_per_frame"] = float(np.mean(n))
        out["depth_median_rel"] = _nanmedian(self.depth_median_rel)
        out["true_flow_median_px"] = _nanmedian(self.true_flow_median_px)
        out["true_depth_median_m"] = _nanmedian(self.true_depth_median_m)
        return out


def _nanmedian(a: np.ndarray) -> float:
    a = np.asarray(a, np.float64)
    return float(np.nanmedian(a)) if np.any(np.isfinite(a)) else float("nan")


def body_poses_at(ground_truth: GroundTruth, t_ns: np.ndarray) -> np.ndarray:
    """(F, 4, 4) true body-to-world poses at ``t_ns`` (positions linear, rotations slerped
    between the ground truth's samples).

    Raises:
        DataError: a time outside the ground truth's span.
    """
    t = np.asarray(ground_truth.t_ns, np.int64)
    t_ns = np.asarray(t_ns, np.int64).reshape(-1)
    if len(t_ns) and (t_ns.min() < t[0] or t_ns.max() > t[-1]):
        raise DataError("frame times outside the ground truth's span")
    s = (t - t[0]) * 1e-9
    q = np.asarray(ground_truth.quaternion, np.float64)
    R = Slerp(s, Rotation.from_quat(q[:, [1, 2, 3, 0]]))((t_ns - t[0]) * 1e-9).as_matrix()
    p = np.stack([np.interp((t_ns - t[0]) * 1e-9, s, ground_truth.position[:, i])
                  for i in range(3)], axis=-1)
    T = np.tile(np.eye(4), (len(t_ns), 1, 1))
    T[:, :3, :3] = R.reshape(-1, 3, 3)
    T[:, :3, 3] = p
    return T


def _undistort(uv: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    if len(uv) == 0:
        return np.zeros((0, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)
    return cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2),
                               np.asarray(cal.K, np.float64),
                               np.asarray(cal.distortion, np.float64), None, None,
                               criteria=crit).reshape(-1, 2)


def _project(P_cam: np.ndarray, cal: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixels of camera-frame points and (N,) bool in front (z > 1 cm)."""
    ahead = P_cam[:, 2] > 1e-2
    if len(P_cam) == 0:
        return np.zeros((0, 2)), ahead
    P = np.where(ahead[:, None], P_cam, np.array([0.0, 0.0, 1.0]))
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                              np.asarray(cal.K, np.float64),
                              np.asarray(cal.distortion, np.float64))
    return uv.reshape(-1, 2), ahead


def _depth_at(depth: np.ndarray, uv: np.ndarray, edge_rel: float) -> np.ndarray:
    """(N,) rendered depth at the nearest pixel of each ``uv``; ``nan`` off the image, where
    none was rendered (0) or on an occluding edge (3 x 3 span above ``edge_rel``)."""
    h, w = depth.shape
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    inside = (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    u, v = np.where(inside, u, 1), np.where(inside, v, 1)
    patch = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], -1)
    d = depth[v, u].astype(np.float64)
    ok = inside & (patch.min(-1) > 0) & ((patch.max(-1) - patch.min(-1)) <= edge_rel * d)
    return np.where(ok, d, np.nan)


def _stats(err: np.ndarray, threshold: float) -> tuple[int, int, float]:
    err = err[np.isfinite(err)]
    return len(err), int(np.sum(err > threshold)), (float(np.median(err)) if len(err)
                                                     else float("nan"))


def match_truth(features: Sequence[FrameFeatures], depth0: Callable[[int], np.ndarray],
                T_WB: np.ndarray, left: CameraCalibration, right: CameraCalibration,
                threshold_px: float = WRONG_PX, edge_rel: float = 0.05) -> MatchTruth:
    """Score a run of the front end against the truth.

    Args:
        features: the tracker's output, one per frame, in order (``FrameFeatures.t`` unused:
            frame ``k`` is ``depth0(k)`` and ``T_WB[k]``).
        depth0: ``k -> (H, W)`` rendered z-depth of the left camera at frame ``k``, metres
            (0 = none), e.g. ``sequence.depth["depth0"].load``.
        T_WB: (F, 4, 4) true body poses at the frames (:func:`body_poses_at`).
        left, right: the cameras' calibrations (``T_BS`` camera to body).
        threshold_px: an error above this (pixels) is a wrong match.
        edge_rel: corners on a depth edge of more than this relative span are not scored.

    Returns:
        A :class:`MatchTruth`.
    """
    T_WB = np.asarray(T_WB, np.float64)
    if len(T_WB) != len(features):
        raise ValueError(f"{len(features)} frames of features but {len(T_WB)} poses")
    T_BC0, T_BC1 = np.asarray(left.T_BS, np.float64), np.asarray(right.T_BS, np.float64)
    T_C1C0 = np.linalg.inv(T_BC1) @ T_BC0
    rows = {k: [] for k in MatchTruth.__dataclass_fields__ if k != "t_ns"}
    t_ns = []
    first: dict[int, np.ndarray] = {}  # id -> world point of its first observation
    prev: dict[int, np.ndarray] = {}  # id -> world point of its previous observation
    for k, f in enumerate(features):
        t_ns.append(int(round(f.t * 1e9)))
        m = np.asarray(f.mask, bool)
        ids, uv = np.asarray(f.ids)[m], np.asarray(f.uv, np.float64)[m]
        T_WC0 = T_WB[k] @ T_BC0
        T_C0W = np.linalg.inv(T_WC0)
        d = _depth_at(np.asarray(depth0(k)), uv, edge_rel)
        xy = _undistort(uv, left)
        P_c = np.concatenate([xy, np.ones((len(xy), 1))], 1) * d[:, None]
        P_w = P_c @ T_WC0[:3, :3].T + T_WC0[:3, 3]

        def reproject(points_w, _T=T_C0W):
            """Pixels in this frame's left camera of world points (nan behind it)."""
            pc = points_w @ _T[:3, :3].T + _T[:3, 3]
            px, ahead = _project(np.nan_to_num(pc), left)
            return np.where((ahead & np.all(np.isfinite(pc), 1))[:, None], px, np.nan)

        nan2 = np.full((len(ids), 3), np.nan)
        P_prev = np.array([prev.get(int(i), nan2[0]) for i in ids]).reshape(-1, 3)
        P_first = np.array([first.get(int(i), nan2[0]) for i in ids]).reshape(-1, 3)
        has_prev = np.array([int(i) in prev for i in ids], bool)
        e_t = np.linalg.norm(uv - reproject(P_prev), axis=1)
        e_t[~has_prev] = np.nan
        e_d = np.linalg.norm(uv - reproject(P_first), axis=1)
        e_d[~has_prev] = np.nan
        for key, e in (("temporal", e_t), ("drift", e_d)):
            n, bad, med = _stats(e, threshold_px)
            rows[f"{key}_n"].append(n)
            rows[f"{key}_bad"].append(bad)
            rows[f"{key}_median_px"].append(med)
        # how far the corners truly moved: this frame's truth projected into the previous
        if k > 0:
            T_C0W_prev = np.linalg.inv(T_WB[k - 1] @ T_BC0)
            pc = P_w @ T_C0W_prev[:3, :3].T + T_C0W_prev[:3, 3]
            px, ahead = _project(np.nan_to_num(pc), left)
            flow = np.linalg.norm(px - uv, axis=1)[ahead & np.isfinite(d)]
            rows["true_flow_median_px"].append(float(np.median(flow)) if len(flow)
                                               else float("nan"))
        else:
            rows["true_flow_median_px"].append(float("nan"))
        rows["true_depth_median_m"].append(_nanmedian(d))

        # stereo: the right observation against the truth, and the triangulated depth
        st = np.asarray(f.stereo_mask, bool)[m]
        P_c1 = P_c[st] @ T_C1C0[:3, :3].T + T_C1C0[:3, 3]
        px1, ahead1 = _project(np.nan_to_num(P_c1), right)
        e_s = np.linalg.norm(np.asarray(f.uv_right, np.float64)[m][st] - px1, axis=1)
        e_s[~(ahead1 & np.isfinite(d[st]))] = np.nan
        n, bad, med = _stats(e_s, threshold_px)
        rows["stereo_n"].append(n)
        rows["stereo_bad"].append(bad)
        rows["stereo_median_px"].append(med)
        z_st = _stereo_depth(xy[st], np.asarray(f.xy_right, np.float64)[m][st],
                             np.linalg.inv(T_C1C0))
        rel = np.abs(z_st / d[st] - 1.0)
        rows["depth_median_rel"].append(_nanmedian(rel))

        for i, pw, ok in zip(ids, P_w, np.isfinite(d), strict=True):
            i = int(i)
            if i not in first:
                first[i] = pw if ok else np.full(3, np.nan)
        prev = {int(i): pw for i, pw in zip(ids, P_w, strict=True)}
    return MatchTruth(np.asarray(t_ns, np.int64),
                      **{k: np.asarray(v, np.int64 if k.endswith(("_n", "_bad"))
                                       else np.float64) for k, v in rows.items()})


def _stereo_depth(xy0: np.ndarray, xy1: np.ndarray, T_C0C1: np.ndarray) -> np.ndarray:
    """(N,) left z-depth of stereo matches by least squares on ``d0 b0 = d1 R b1 + t``
    (``nan`` for near-parallel rays)."""
    if len(xy0) == 0:
        return np.zeros(0)
    R, t = T_C0C1[:3, :3], T_C0C1[:3, 3]
    b0 = np.concatenate([xy0, np.ones((len(xy0), 1))], 1)
    b1 = np.concatenate([xy1, np.ones((len(xy1), 1))], 1) @ R.T
    A = np.stack([b0, -b1], -1)  # (N, 3, 2)
    AtA = np.einsum("nki,nkj->nij", A, A)
    Atb = np.einsum("nki,k->ni", A, t)
    det = AtA[:, 0, 0] * AtA[:, 1, 1] - AtA[:, 0, 1] ** 2
    d0 = (AtA[:, 1, 1] * Atb[:, 0] - AtA[:, 0, 1] * Atb[:, 1]) / np.where(det > 1e-12, det, 1)
    return np.where(det > 1e-12, d0, np.nan)
