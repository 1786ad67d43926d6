"""What ``uavcal run`` writes into its output folder, under fixed names (:data:`OUTPUT_FILES`),
and the content of ``metrics.json`` (:func:`build_metrics`).

Positions in ``targets.csv`` and ``setpoints.csv`` are in the trajectory's (the VIO's) world
frame, as ``trajectory.txt``; only the metrics are computed after aligning to the ground
truth (:mod:`uavcal_jax.pipeline.run_metrics`). The tables' format is
:mod:`uavcal_jax.data.run_tables`.
"""

from __future__ import annotations

import collections
import json
import time
from pathlib import Path

import numpy as np

from uavcal_jax.argtypes import to_builtin
from uavcal_jax.config import write_config
from uavcal_jax.data.run_tables import write_setpoints, write_targets
from uavcal_jax.data.tum import write_tum
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.run_metrics import Evaluation, statistics
from uavcal_jax.pipeline.targets import TargetResult
from uavcal_jax.track import PREDICTING, TRACKING

__all__ = ["FIGURE_FILES", "OUTPUT_FILES", "build_metrics", "format_run_summary", "target_rows",
           "write_outputs"]

#: The files of the output folder, by role.
OUTPUT_FILES = {"trajectory": "trajectory.txt", "targets": "targets.csv",
                "setpoints": "setpoints.csv", "metrics": "metrics.json",
                "config": "config.json"}
#: The figures (:func:`uavcal_jax.plots.plot_run`), by role.
FIGURE_FILES = {"top_view": "top_view.png", "frames": "frames.png",
                "localisation_error": "localisation_error.png"}


def target_rows(times_ns: np.ndarray, target: TargetResult, lost_after_s: float) -> list[tuple]:
    """``targets.csv``'s rows (:func:`uavcal_jax.data.run_tables.write_targets`), time order.

    ``raw``: each located box, confidence its detection score. ``filtered``: each frame the
    filter tracks or predicts the target; confidence the last used detection's score, fading
    linearly to 0 over ``lost_after_s`` without a measurement.
    """
    rows = []
    track, name = target.track_id, target.class_name
    if track is None:
        return rows
    raw_at = {int(k): i for i, k in enumerate(target.raw_frames)}
    f = target.filtered
    last_score, last_t = 0.0, None
    t_s = (times_ns - times_ns[0]) * 1e-9
    for k, t_ns in enumerate(times_ns):
        i = raw_at.get(k)
        if i is not None:
            rows.append((t_ns, track, name, target.raw_points[i], np.diag(target.raw_cov[i]),
                         float(target.scores[k]), "raw"))
        if f.status[k] == TRACKING:
            last_score, last_t = float(target.scores[k]), t_s[k]
        if f.status[k] in (TRACKING, PREDICTING) and np.all(np.isfinite(f.position[k])):
            age = 0.0 if last_t is None else t_s[k] - last_t
            conf = last_score * max(0.0, 1.0 - age / lost_after_s)
            rows.append((t_ns, track, name, f.position[k], np.diag(f.covariance[k])[:3],
                         conf, "filtered"))
    return rows


def build_metrics(*, recording, fmt, vio, offset, detections, detected_frames, class_names,
                  target: TargetResult, evaluation: Evaluation, follow, ms_per_frame, compile_s,
                  seconds, notes) -> dict:
    """``metrics.json``: ``ate_m``, ``offset``, ``target_error_m``, ``follow``,
    ``ms_per_frame`` (and ``compile_s``) as the issue names them, and what explains them:
    ``vio`` (frames, poses, resets), ``detections``, ``localisation``, ``omitted`` (the
    metrics left out for want of a truth, and why), ``seconds`` per step, ``notes``."""
    truth = offset["true"]
    estimate = np.asarray(offset["estimate"], np.float64)
    # the boxes the tracker took (a track id): not a doubtful box that continued no track
    # (ByteTrack's second round) or a part of a larger box
    tracked = [None if d is None or ids is None else np.asarray(ids) >= 0
               for d, ids in zip(detections, target.track_ids, strict=True)]
    by_class = collections.Counter(int(c) for d, keep in zip(detections, tracked, strict=True)
                                   if keep is not None for c in np.asarray(d.classes)[keep])
    untracked = sum(int((~keep).sum()) for keep in tracked if keep is not None)
    target_error = None
    if evaluation.truth is not None:
        target_error = {"raw": statistics(evaluation.raw_errors),
                        "filtered": statistics(evaluation.filtered_errors)}
    traj = vio.trajectory()
    return {
        "sequence": str(recording), "format": fmt,
        "ate_m": evaluation.ate_m,
        "offset": {"estimate": estimate.tolist(),
                   "true": None if truth is None else np.asarray(truth).tolist(),
                   "error": None if truth is None else (estimate - truth).tolist(),
                   "method": offset["method"], "label": offset["label"],
                   "removed": offset["removed"]},
        "target_error_m": target_error,
        "follow": follow,
        "ms_per_frame": ms_per_frame,
        "compile_s": compile_s,
        "vio": {"frames": len(vio.frames), "poses": len(traj), "resets": vio.resets,
                "unreadable_frames": vio.unreadable},
        "detections": {"frames_run": detected_frames,
                       "frames_with_detections": sum(1 for keep in tracked
                                                     if keep is not None and keep.any()),
                       "boxes": int(sum(by_class.values())),
                       "untracked_boxes": untracked,
                       "by_class": {class_names[c] if 0 <= c < len(class_names) else str(c): n
                                    for c, n in sorted(by_class.items())},
                       "followed_class": target.class_name, "followed_track": target.track_id,
                       "true_track": evaluation.true_track_id,
                       "target_switches": evaluation.target_switches},
        "localisation": {**target.localisation, "located": len(target.raw_frames),
                         "not_located": target.not_located},
        "omitted": evaluation.omitted,
        "seconds": seconds,
        "notes": notes,
    }


def write_outputs(out_dir: Path, *, trajectory, times_ns, target: TargetResult,
                  evaluation: Evaluation, setpoints, metrics: dict, config: RunConfig,
                  inputs: dict, t_start: float) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` into ``out_dir`` (created); ``metrics["seconds"]["total"]``
    is set last (from ``t_start``, a ``time.perf_counter()``). Returns the paths by role."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {k: out_dir / v for k, v in OUTPUT_FILES.items()}
    write_tum(paths["trajectory"], trajectory)
    write_targets(paths["targets"], target_rows(np.asarray(times_ns), target,
                                                config.filter.lost_after))
    write_setpoints(paths["setpoints"], times_ns, setpoints.position, setpoints.yaw)
    write_config(paths["config"], config, inputs=inputs)
    metrics["seconds"]["total"] = time.perf_counter() - t_start
    paths["metrics"].write_text(json.dumps(metrics, indent=1, default=to_builtin) + "\n")
    return paths


def format_run_summary(metrics: dict, out_dir, figures: dict) -> str:
    """The main figures of ``metrics.json`` (:func:`build_metrics`), a few lines for a person
    (``uavcal run`` and ``uavcal demo`` print them; ``--json`` prints it all)."""
    m = metrics
    lines = [f"{m['vio']['poses']} poses from {m['vio']['frames']} frames, "
             f"{m['vio']['resets']} resets -> {out_dir}"]
    o = m["offset"]
    lines.append(f"IMU offset {'removed' if o.get('removed', True) else 'estimated'} "
                 f"({o['method']}): "
                 + " ".join(f"{v:.4f}" for v in o["estimate"]))
    if o["true"] is not None:
        lines.append("  true: " + " ".join(f"{v:.4f}" for v in o["true"]) + "  error: "
                     + " ".join(f"{e - t:.4f}" for e, t in zip(o["estimate"], o["true"],
                                                               strict=True))
                     + "  (gyro rad/s, accel m/s^2)")
    if m["ate_m"] is not None:
        lines.append(f"ATE rmse {m['ate_m']['rmse']:.4f} m ({m['ate_m']['alignment']} "
                     "alignment)")
    d = m["detections"]
    lines.append(f"detections: {d['boxes']} in {d['frames_with_detections']} of "
                 f"{d['frames_run']} frames; following {d['followed_class']} track "
                 f"{d['followed_track']}; {m['localisation']['located']} boxes located "
                 f"({m['localisation']['mode']})")
    err = m["target_error_m"]
    for kind in ("raw", "filtered"):
        if err is not None and err[kind] is not None:
            e = err[kind]
            lines.append(f"target error {kind}: median {e['median']:.3f} m, rmse "
                         f"{e['rmse']:.3f} m, max {e['max']:.3f} m ({e['count']} frames)")
    f = m["follow"]
    if f.get("distance_error_vs_true_m"):
        lines.append(f"follow (set-points against the true target): distance error median "
                     f"{f['distance_error_vs_true_m']['median']:.2f} m, height error median "
                     f"{f['height_error_vs_true_m']['median']:.2f} m; set-point speed max "
                     f"{f['max_setpoint_speed_mps']:.2f} m/s, yaw rate max "
                     f"{f['max_yaw_rate_radps']:.2f} rad/s")
    for key, reason in m["omitted"].items():
        lines.append(f"{key}: omitted ({reason})")
    ms = m["ms_per_frame"]
    parts = [f"{k} {ms[k]['mean']:.1f}" for k in ("vio_wall", "detect", "locate", "filter",
                                                   "follow", "pipeline") if ms.get(k)]
    lines.append("ms per frame (steady state): " + ", ".join(parts))
    lines.append("figures: " + ", ".join(str(p) for p in figures.values()))
    return "\n".join(lines)
