"""The figures of a ``uavcal run`` (``metrics.json``): accuracy against the ground truth where
the recording has it, the follow law's behaviour, and the time per frame of each stage.

Accuracy needs the truth in the ground truth's world frame, and the run estimates in the
VIO's: the estimated trajectory is aligned to the ground truth over yaw and translation, the
four directions a VIO cannot observe (:data:`RUN_ALIGNMENT`; at the first pose where a hover
or a vertical flight leaves it undetermined) and the *same* transform is applied
to the estimated target positions and set-points before they are compared with the target's
true world track (``target0/track.csv``, or the labels' positions where only those exist).
Each frame's true target is the labelled one under the followed box (carried over the frames
without a box), so the error is that of the target measured; the followed target's changes
are counted as identity switches. Whatever needs a truth the recording lacks is ``None`` in
the metrics, with the reason under ``omitted``.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np

from uavcal_jax.data.sequence import GroundTruth, Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.targets import TargetResult
from uavcal_jax.track import LOST, PREDICTING, TRACKING, UNSEEN
from uavcal_jax.track.associate import box_iou
from uavcal_jax.track.follow import wrap_angle
from uavcal_jax.vio.trajectory_metrics import Alignment, ate

__all__ = ["RUN_ALIGNMENT", "Evaluation", "evaluate", "follow_metrics", "stage_timings",
           "statistics"]

#: The run's alignment of its estimates to the truth (ATE, target, set-points): yaw and
#: translation. A full SE(3) Umeyama fit is free to roll the trajectory about a straight leg
#: (it only fits positions on the line), and carries a target seen 8 m off the line 5-6 m
#: from its place (measured on the demo's 8 s straight flight: 5.8 m with perfect boxes).
RUN_ALIGNMENT = "posyaw"


def statistics(errors) -> dict | None:
    """``median``, ``rmse``, ``max``, ``mean`` and ``count`` of (K,) errors; ``None`` if K=0."""
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return None
    return {"median": float(np.median(e)), "rmse": float(np.sqrt(np.mean(e * e))),
            "max": float(np.max(e)), "mean": float(np.mean(e)), "count": int(e.size)}


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """The run against the truth (arrays per left frame ``T``, world = the ground truth's).

    Attributes:
        alignment: VIO world -> ground-truth world (``None`` without ground truth).
        ate_m: the trajectory's ATE (``rmse``, ``mean``, ``median``, ``max`` metres,
            ``matched`` poses, ``alignment``), ``None`` without ground truth.
        true_track_id: the labelled target followed most (``None``: unknown).
        truth: (T, 3) per frame the true position of the labelled target followed then (NaN
            where unknown), or ``None``.
        target_switches: the changes of the labelled target followed (``None``: unknown).
        raw_points, filtered, setpoints: the run's positions mapped by ``alignment`` (as
            they are without one).
        raw_errors: (R,) per located box, metres; filtered_errors: (T,) per frame (NaN
            where not evaluated: no estimate, lost, no truth).
        omitted: ``{metric: reason}``.
    """

    alignment: Alignment | None
    ate_m: dict | None
    true_track_id: int | None
    truth: np.ndarray | None
    target_switches: int | None
    raw_points: np.ndarray
    filtered: np.ndarray
    setpoints: np.ndarray
    raw_errors: np.ndarray
    filtered_errors: np.ndarray
    omitted: dict[str, str]


def _apply(a: Alignment | None, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if a is None:
        return points
    return a.scale * points @ a.rotation.T + a.translation


def _ate(trajectory: GroundTruth, gt: GroundTruth) -> tuple[Alignment, dict]:
    """The alignment and the ATE summary (as ``uavcal vio``'s ``ate_m``)."""
    try:
        result = ate(trajectory, gt, alignment=RUN_ALIGNMENT)
    except DataError:  # a hover or a vertical flight: align at the first pose
        result = ate(trajectory, gt, alignment="origin")
    s = result.translation
    return result.alignment, {"rmse": s.rmse, "mean": s.mean, "median": s.median,
                              "max": s.max, "matched": s.count,
                              "alignment": result.alignment.method}


def _true_target(sequence: Sequence, target: TargetResult
                 ) -> tuple[int | None, np.ndarray | None, int, str]:
    """``(track id, (T, 3) truth, switches, reason)`` of the followed target in the labels.

    Each frame's truth is the labelled target under the followed box (IoU over 0.3), carried
    over the frames without one from the last frame with one (from the first, before it): the
    localisation is scored against the target it measured, as MOTP scores a tracker. The
    track id is the one under most boxes; ``switches`` counts the changes of the labelled
    target followed (MOT's identity switches)."""
    labels = sequence.targets
    if labels is None or len(labels) == 0:
        return None, None, 0, "the recording has no target labels (target0)"
    if target.track_id is None:
        return None, None, 0, f"no {target.class_name} was detected"
    t_ns = sequence.camera("cam0").t_ns
    under = np.full(len(t_ns), -1, np.int64)
    left = labels.camera == "cam0"
    for k in np.flatnonzero(np.all(np.isfinite(target.boxes), axis=1)):
        rows = np.flatnonzero(left & (labels.t_ns == t_ns[k]))
        if rows.size:
            iou = box_iou(target.boxes[k][None], labels.box[rows])[0]
            if iou.max() > 0.3:
                under[k] = int(labels.track_id[rows[np.argmax(iou)]])
    known = np.flatnonzero(under >= 0)
    if not known.size:
        return None, None, 0, "no labelled target overlaps the followed track's boxes"
    track = collections.Counter(under[known].tolist()).most_common(1)[0][0]
    # each frame's target: the last one under a box so far (the first one before any)
    followed = under[known][np.clip(np.searchsorted(known, np.arange(len(t_ns)), "right") - 1,
                                    0, None)]
    switches = int(np.sum(np.diff(under[known]) != 0))
    truth = np.full((len(t_ns), 3), np.nan)
    tracks = labels.tracks
    columns = {} if tracks is None else {int(i): j for j, i in enumerate(tracks.track_id)}
    if tracks is not None and set(followed.tolist()) <= set(columns):
        index = {int(t): i for i, t in enumerate(tracks.t_ns)}
        for k, t in enumerate(t_ns):
            i = index.get(int(t))
            if i is not None:
                truth[k] = tracks.position[i, columns[int(followed[k])]]
    else:  # labels only: the target's position where it is labelled
        index = {int(t): k for k, t in enumerate(t_ns)}
        for r in np.flatnonzero(left):
            k = index.get(int(labels.t_ns[r]))
            if k is not None and labels.track_id[r] == followed[k]:
                truth[k] = labels.position[r]
    return track, truth, switches, ""


def evaluate(sequence: Sequence, trajectory: GroundTruth, target: TargetResult,
             setpoints: np.ndarray) -> Evaluation:
    """Align and compare (the module docstring); ``setpoints`` (T, 3) in the VIO's world."""
    omitted: dict[str, str] = {}
    gt = sequence.ground_truth
    alignment = ate_m = None
    if gt is None or len(gt) == 0:
        omitted["ate_m"] = "the recording has no ground truth"
    elif len(trajectory) < 3:
        omitted["ate_m"] = "fewer than 3 VIO poses"
    else:
        alignment, ate_m = _ate(trajectory, gt)
    track, truth, switches, reason = _true_target(sequence, target)
    if alignment is None:
        reason = omitted.get("ate_m", reason)
        truth = None
    if truth is None:
        omitted["target_error_m"] = reason
    raw = _apply(alignment, target.raw_points)
    filtered = _apply(alignment, target.filtered.position)
    sp = _apply(alignment, setpoints)
    raw_err = np.full(len(raw), np.nan)
    filt_err = np.full(len(filtered), np.nan)
    if truth is not None:
        raw_err = np.linalg.norm(raw - truth[target.raw_frames], axis=1)
        live = np.isin(target.filtered.status, (TRACKING, PREDICTING))
        filt_err = np.where(live, np.linalg.norm(filtered - truth, axis=1), np.nan)
    return Evaluation(alignment, ate_m, track, truth, None if truth is None else switches, raw,
                      filtered, sp, raw_err, filt_err, omitted)


def follow_metrics(times_s: np.ndarray, setpoints: np.ndarray, yaw: np.ndarray,
                   target: TargetResult, evaluation: Evaluation, config: RunConfig,
                   detected_frames: int) -> dict:
    """The follow law's figures: set-point speed and yaw rate (maxima), the share of frames
    with a detection, a located box and a filtered estimate, the filter's losses, and (with
    the truth) the set-points' horizontal distance and height errors against the desired
    stand-off from the *true* target (over frames where the set-point follows an estimate)."""
    T = len(times_s)
    dt = np.diff(times_s)
    step = np.linalg.norm(np.diff(setpoints, axis=0), axis=1)
    ok = dt > 0
    speed = step[ok] / dt[ok] if ok.any() else np.zeros(0)
    yaw_rate = np.abs(wrap_angle(np.diff(yaw)))[ok] / dt[ok] if ok.any() else np.zeros(0)
    status = target.filtered.status
    lost = (status == LOST)
    losses = int(np.sum(lost[1:] & ~lost[:-1]) + (lost[0] if T else 0))
    out = {
        "max_setpoint_speed_mps": float(speed.max()) if speed.size else 0.0,
        "max_yaw_rate_radps": float(yaw_rate.max()) if yaw_rate.size else 0.0,
        "fraction_detected": float(np.isfinite(target.scores).sum() / max(detected_frames, 1)),
        "fraction_located": float(len(target.raw_frames) / max(detected_frames, 1)),
        "fraction_filtered": float(np.isin(status, (TRACKING, PREDICTING)).mean()) if T else 0.0,
        "filter_status": {name: int(np.sum(status == code)) for name, code in
                          (("tracking", TRACKING), ("predicting", PREDICTING), ("lost", LOST),
                           ("unseen", UNSEEN))},
        "gated": int(np.sum(target.filtered.gated)),
        "losses": losses,
        "distance_m": config.follow.distance, "height_m": config.follow.height,
    }
    known = status != UNSEEN
    for name, ref in (("vs_true", evaluation.truth), ("vs_estimate", evaluation.filtered)):
        if ref is None or not known.any():
            out[f"distance_error_{name}_m"] = out[f"height_error_{name}_m"] = None
            continue
        use = known & np.all(np.isfinite(ref), axis=1)
        horizontal = np.linalg.norm(evaluation.setpoints[use, :2] - ref[use, :2], axis=1)
        height = evaluation.setpoints[use, 2] - ref[use, 2] - config.follow.height
        out[f"distance_error_{name}_m"] = statistics(np.abs(horizontal - config.follow.distance))
        out[f"height_error_{name}_m"] = statistics(np.abs(height))
    return out


def _ms(values) -> dict | None:
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    return {"mean": float(v.mean()), "median": float(np.median(v)),
            "p95": float(np.percentile(v, 95)), "frames": int(v.size)}


def stage_timings(vio_timings: list[dict], detect_ms: np.ndarray, target: TargetResult,
                  frames: int, every: int, warmup: int
                  ) -> tuple[dict, dict]:
    """``(ms_per_frame, compile_s)``.

    ``ms_per_frame``: per stage in the steady state (the first ``warmup`` frames of each
    left out), ``mean``/``p95`` ms: the VIO's own stages (``vio_frontend``, ``vio_solve``,
    ``vio_marginalize``, ``vio_total``) and ``vio_wall`` (wall-clock time per frame while the
    detector ran beside it), ``detect`` (per detected frame: image load and network),
    ``locate`` (per located box, with ``boxes_per_frame``: association locates every box of
    the class followed that could continue a track, not the followed box alone), ``filter``
    and ``follow`` (the tracker's step per frame), and ``pipeline``: what
    a frame costs when the detector runs concurrently with the VIO, ``max(vio_wall, detect /
    every) + locate * boxes_per_frame + filter + follow`` (of the means, and of the medians:
    on a shared CPU the mean carries other processes' stalls).
    ``compile_s``: the first call's extra time over the steady state, seconds, per stage.
    """
    rows = vio_timings[max(warmup, 1):]
    ms = {f"vio_{k}": _ms([r.get(k, np.nan) for r in rows])
          for k in ("frontend", "solve", "marginalize", "total", "wall")}
    ms["detect"] = _ms(detect_ms[warmup:])
    ms["locate"] = _ms(target.locate_ms[warmup:])
    boxes_per_frame = target.locate_ms.size / max(frames, 1)
    if ms["locate"] is not None:
        ms["locate"]["boxes_per_frame"] = boxes_per_frame
    ms["filter"] = _ms(target.filter_ms[warmup:])
    ms["follow"] = _ms(target.follow_ms[warmup:])

    def mean(key, stat="mean"):
        return 0.0 if ms[key] is None else ms[key].get(stat, ms[key]["mean"])

    ms["pipeline"] = {stat: max(mean("vio_wall", stat), mean("detect", stat) / every)
                      + mean("locate", stat) * boxes_per_frame + mean("filter", stat)
                      + mean("follow", stat)
                      for stat in ("mean", "median")} | {"p95": None, "frames": frames}
    first_vio = vio_timings[0].get("total", np.nan) if vio_timings else np.nan
    compile_s = {
        "vio": None if not np.isfinite(first_vio) else max(0.0, (first_vio - mean("vio_total"))
                                                           / 1e3),
        "detect": None if detect_ms.size == 0 else max(0.0, (detect_ms[0] - mean("detect"))
                                                       / 1e3),
        "locate": None if target.locate_ms.size == 0 else max(
            0.0, (target.locate_ms[0] - mean("locate")) / 1e3),
        "filter": None if target.filter_ms.size == 0 else max(
            0.0, (target.filter_ms[0] - mean("filter")) / 1e3),
        "follow": None if target.follow_ms.size == 0 else max(
            0.0, (target.follow_ms[0] - mean("follow")) / 1e3),
    }
    return ms, compile_s
