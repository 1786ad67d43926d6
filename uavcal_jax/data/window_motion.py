"""Motion inputs of training windows: per-frame IMU means, an orientation per frame (from the
ground truth or chained from visual relative rotations) and the full-rate gyro of each frame
interval beside the camera's rotation over it (:meth:`uavcal_jax.data.windows.WindowSet.motion`,
the calibrator's rotation-residual tokens).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

if TYPE_CHECKING:
    from uavcal_jax.data.windows import WindowSet

__all__ = ["chain_orientations", "interval_mean_imu", "interval_motion", "oracle_orientations"]


def interval_mean_imu(frame_t_ns: np.ndarray, span_ns: int, imu_t_ns: np.ndarray,
                      imu: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """``(F, C)`` the mean of the IMU rows ``imu (N, C)`` with ``t_f - span_ns < t <= t_f``
    for each frame time ``t_f`` (``frame_t_ns (F,)``); a frame with no such sample takes
    its ``nearest (F,)`` row. Float64 prefix sums."""
    csum = np.concatenate([np.zeros((1, imu.shape[1])), np.cumsum(imu, axis=0)])
    lo = np.searchsorted(imu_t_ns, frame_t_ns - span_ns, side="right")
    hi = np.searchsorted(imu_t_ns, frame_t_ns, side="right")
    count = hi - lo
    mean = (csum[hi] - csum[lo]) / np.maximum(count, 1)[:, None]
    return np.where((count > 0)[:, None], mean, imu[nearest])


def oracle_orientations(ground_truth, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth's body-to-world rotation ``(F, 3, 3)`` slerped at ``t_ns (F,)`` and
    the segment per frame (``0``; ``-1`` outside the ground truth's time span: identity)."""
    t_ns = np.asarray(t_ns, np.int64)
    R = np.broadcast_to(np.eye(3), (t_ns.size, 3, 3)).copy()
    seg = np.full(t_ns.size, -1, np.int64)
    if ground_truth is None or len(ground_truth) < 2:
        return R, seg
    gt_t = np.asarray(ground_truth.t_ns, np.int64)
    q = np.asarray(ground_truth.quaternion, np.float64)
    inside = (t_ns >= gt_t[0]) & (t_ns <= gt_t[-1])
    if inside.any():
        rot = Rotation.from_quat(q[:, [1, 2, 3, 0]])  # scipy: x, y, z, w
        # Relative times in float64 seconds: absolute nanoseconds lose precision.
        slerp = Slerp((gt_t - gt_t[0]) * 1e-9, rot)
        R[inside] = slerp((t_ns[inside] - gt_t[0]) * 1e-9).as_matrix()
        seg[inside] = 0
    return R, seg


def chain_orientations(t_ns: np.ndarray, visual_rotations) -> tuple[np.ndarray, np.ndarray]:
    """Orientations ``(F, 3, 3)`` and segments ``(F,)`` of the frames at ``t_ns (F,)``
    (ascending) from relative rotations ``visual_rotations`` (fields ``t0_ns``, ``t1_ns``,
    ``R`` body frame at ``t0`` from ``t1``, ``valid``): a frame reached by a valid pair
    from an earlier frame of a segment continues it (``R_1 = R_0 @ R_pair``), any other
    frame starts a new segment at the identity."""
    t_ns = np.asarray(t_ns, np.int64)
    pairs = {}
    for t0, t1, R, ok in zip(np.asarray(visual_rotations.t0_ns, np.int64),
                             np.asarray(visual_rotations.t1_ns, np.int64),
                             np.asarray(visual_rotations.R, np.float64),
                             np.asarray(visual_rotations.valid, bool), strict=True):
        if ok and t0 < t1:
            pairs.setdefault(int(t1), (int(t0), R))
    out = np.broadcast_to(np.eye(3), (t_ns.size, 3, 3)).copy()
    seg = np.zeros(t_ns.size, np.int64)
    where = {}
    n_seg = 0
    for k, t in enumerate(t_ns.tolist()):
        link = pairs.get(t)
        j = where.get(link[0]) if link is not None else None
        if j is not None:
            out[k] = out[j] @ link[1]
            seg[k] = seg[j]
        else:
            seg[k] = n_seg
            n_seg += 1
        where[t] = k
    return out, seg


def interval_motion(ws: WindowSet, indices, cap: int | None = None) -> dict[str, np.ndarray]:
    """:meth:`WindowSet.motion` (its docstring gives the outputs)."""
    if ws.frame_R is None:
        raise ValueError("these windows have no frame orientations "
                         "(WindowConfig.rotations='none')")
    S = ws.interval_cap if cap is None else int(cap)
    indices = np.asarray(indices, np.int64).reshape(-1)
    idx, mask = ws.frame_index[indices], ws.frame_mask[indices]
    safe = np.maximum(idx, 0)
    t = ws.frame_t_ns[safe]
    seg = np.where(mask, ws.frame_R_segment[safe], -1)
    valid = np.zeros(mask.shape, bool)
    valid[:, 1:] = (seg[:, 1:] >= 0) & (seg[:, 1:] == seg[:, :-1])
    a = np.concatenate([t[:, :1], t[:, :-1]], axis=1)  # interval start (slot 0: empty)
    b = np.where(valid, t, a)
    imu_t = ws.imu_t_ns
    n = imu_t.size
    first = np.clip(np.searchsorted(imu_t, a, side="right") - 1, 0, n - 1)
    last = np.searchsorted(imu_t, b, side="left") - 1
    valid &= (last - first + 1 <= S) & (last >= first)
    j = first[..., None] + np.arange(S)  # (B, T, S)
    real = valid[..., None] & (j <= last[..., None])
    jc = np.minimum(j, n - 1)
    t_end = np.where(jc + 1 < n, imu_t[np.minimum(jc + 1, n - 1)], np.iinfo(np.int64).max)
    lo = np.maximum(imu_t[jc], a[..., None])
    hi = np.minimum(t_end, b[..., None])
    dt = np.where(real, np.maximum(hi - lo, 0), 0) * 1e-9
    gyro = np.where(real[..., None], ws.gyro[jc], 0.0)
    R = ws.frame_R[safe]
    rel = np.einsum("btji,btjk->btik", R[:, :-1], R[:, 1:])
    rot = np.broadcast_to(np.eye(3), idx.shape + (3, 3)).copy()
    rot[:, 1:] = rel
    rot[~valid] = np.eye(3)
    return {"gyro_seq": gyro.astype(np.float32), "dt_seq": dt.astype(np.float32),
            "rot_cam": rot.astype(np.float32), "rot_mask": valid}
