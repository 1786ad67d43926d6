"""The figures of a closed-loop flight (:mod:`uavcal_jax.pipeline.closed_loop`): the pose's
world aligned to the truth, and the follow, view, loss and localisation errors against the
simulator's ground truth over the window after the car has started.
"""

from __future__ import annotations

import collections

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.run_metrics import RUN_ALIGNMENT, statistics
from uavcal_jax.track import LOST, TRACKING
from uavcal_jax.track.follow import wrap_angle
from uavcal_jax.vio.trajectory_metrics import ate

__all__ = ["align_to_truth", "flight_metrics"]


def _episodes(mask: np.ndarray, dt: float) -> list[float]:
    """Durations (seconds) of the runs of True in ``mask``."""
    out, run = [], 0
    for m in list(mask) + [False]:
        if m:
            run += 1
        elif run:
            out.append(run * dt)
            run = 0
    return out


def align_to_truth(t_ns: np.ndarray, pose_p: np.ndarray, pose_R: np.ndarray,
                   true_p: np.ndarray, true_R: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     dict | None]:
    """``(R, t, ate)``: the rigid alignment (:data:`~uavcal_jax.pipeline.run_metrics.
    RUN_ALIGNMENT`, else the origin's) of the pose's positions (F, 3) and rotations (F, 3, 3)
    (NaN where none) to the true ones at ``t_ns`` (F,), and the ATE figures (``None`` with
    fewer than 3 poses: the identity)."""
    have = np.all(np.isfinite(pose_p), axis=1)
    if have.sum() < 3:
        return np.eye(3), np.zeros(3), None
    est = _trajectory(t_ns[have], pose_p[have], pose_R[have])
    gt = _trajectory(t_ns[have], true_p[have], true_R[have])
    try:
        res = ate(est, gt, alignment=RUN_ALIGNMENT)
    except DataError:
        res = ate(est, gt, alignment="origin")
    s = res.translation
    return res.alignment.rotation, res.alignment.translation, {
        "rmse": s.rmse, "mean": s.mean, "median": s.median, "max": s.max,
        "alignment": res.alignment.method}


def flight_metrics(*, follow, dt: float, window: np.ndarray, window_text: str, drone, drone_yaw,
                   target, in_view, raw, filtered, status, unmeasured, ms: dict,
                   warmup: int) -> dict:
    """The flight's figures over the frames ``window`` (F,) bool.

    Args:
        follow: the :class:`~uavcal_jax.track.FollowConfig` flown.  dt: seconds per frame.
        window_text: what the window is, for the report.
        drone: (F, 3) true body positions; drone_yaw: (F,) true quadrotor headings.
        target: (F, 3) the car's true centre; in_view: (F,) bool.
        raw, filtered: (F, 3) the located and filtered target, aligned to the true world.
        status: (F,) filter status codes.  unmeasured: (F,) why a frame has no measurement.
        ms: per stage, (F,) milliseconds.  warmup: frames left out of the timings' means.
    """
    w = window
    rel = target[:, :2] - drone[:, :2]
    dist_err = np.abs(np.linalg.norm(rel, axis=1) - follow.distance)
    height_err = drone[:, 2] - (target[:, 2] + follow.height)
    yaw_err = np.asarray(wrap_angle(drone_yaw - np.arctan2(rel[:, 1], rel[:, 0])))
    raw_err = np.linalg.norm(raw - target, axis=1)
    filt_err = np.linalg.norm(filtered - target, axis=1)
    seen = np.cumsum(status == TRACKING) > 0
    gaps = _episodes(w & seen & (status != TRACKING), dt)
    lost = _episodes(w & (status == LOST), dt)
    F = len(status)
    metrics = {
        "frames": int(F), "evaluated_frames": int(w.sum()), "window": window_text,
        "distance_error_m": _stats(dist_err[w]),
        "height_error_m": _stats(np.abs(height_err[w])),
        "yaw_error_deg": _stats(np.degrees(np.abs(yaw_err[w]))),
        "in_view_fraction": float(np.mean(in_view[w])) if w.any() else None,
        "in_view_fraction_all": float(np.mean(in_view)),
        "measured_fraction": float(np.mean(status[w] == TRACKING)) if w.any() else None,
        "losses": {"count": len(gaps), "durations_s": gaps,
                   "longest_s": max(gaps, default=0.0),
                   "lost_status_episodes_s": lost,
                   "frames_by_reason": dict(collections.Counter(
                       str(r) for r in unmeasured[w & seen & (status != TRACKING)] if r))},
        "localisation_rmse_m": {"raw": _stats(raw_err[w]), "filtered": _stats(filt_err[w])},
        "ms_per_frame": {s: {"mean": float(np.mean(v[warmup:])) if warmup < F else None,
                             "first": float(v[0])} for s, v in ms.items()},
    }
    metrics["ms_per_frame"]["total"] = {
        "mean": float(np.mean(sum(ms.values())[warmup:])) if warmup < F else None}
    return metrics


def _trajectory(t_ns: np.ndarray, position: np.ndarray, R: np.ndarray) -> GroundTruth:
    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]  # w x y z
    return GroundTruth(np.asarray(t_ns, np.int64), np.asarray(position, np.float64), q)


def _stats(errors) -> dict | None:
    s = statistics(errors)
    return None if s is None else {k: s[k] for k in ("mean", "median", "rmse", "max", "count")}
