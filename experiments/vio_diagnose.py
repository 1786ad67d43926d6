"""Diagnose the stereo VIO on a simulated flight against its ground truth.

Runs the estimator frame by frame over a simulated EuRoC folder (``uavcal simulate`` output,
with ``depth0``), keeps the front end's features, and reports:

* the front end's wrong-match shares (:func:`uavcal_jax.vio.track_truth.match_truth`):
  frame-to-frame, along each track, left-right, the stereo depth's relative error, how far
  the corners truly moved per frame and how deep they are;
* the initialisation against the truth at the first pose and after ``--init-s`` seconds:
  gravity (tilt) error, velocity error, and the scale of the estimated displacement;
* the run: keyframes, resets, the window cost early and late, ATE (SE(3)) and path length.

One JSON line per flight (and, with ``--csv``, the per-frame table). Example::

    uavcal simulate --out /tmp/o45 --trajectory outdoor_45_1.txt --start 2 --duration 8 \\
        --seed 4 --resolution 376x240
    python experiments/vio_diagnose.py /tmp/o45 --csv /tmp/o45.diag.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import sys

import numpy as np

from uavcal_jax.config import apply_overrides
from uavcal_jax.data.read import read_sequence
from uavcal_jax.vio import estimator
from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.run import VioResult, one_blas_thread, stereo_pairs
from uavcal_jax.vio.track_truth import body_poses_at, match_truth
from uavcal_jax.vio.trajectory_metrics import ate


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def init_report(frames, T_WB: np.ndarray, v_true: np.ndarray, init_s: float) -> dict:
    """Gravity, velocity and scale of the estimate against the truth at the first pose and
    ``init_s`` seconds later. The world frames differ by a yaw and a translation (the
    estimator's origin and yaw are its own), so compared are: the gravity direction in the
    body frame, the speed and the velocity's angle to gravity (yaw-free), and the length of
    the displacement since the first pose."""
    idx = [i for i, f in enumerate(frames) if f.has_pose]
    if not idx:
        return {}
    i0 = idx[0]
    t0 = frames[i0].t_ns
    out = {}
    for name, i in (("first", i0), (f"after_{init_s:g}s", next(
            (j for j in idx if (frames[j].t_ns - t0) * 1e-9 >= init_s), idx[-1]))):
        f = frames[i]
        g_est = f.rotation.T @ np.array([0.0, 0.0, -1.0])  # gravity in the body, estimated
        g_true = T_WB[i, :3, :3].T @ np.array([0.0, 0.0, -1.0])
        v_e, v_t = f.velocity, v_true[i]
        d_e = np.linalg.norm(f.position - frames[i0].position)
        d_t = np.linalg.norm(T_WB[i, :3, 3] - T_WB[i0, :3, 3])
        out[name] = {
            "frame": i, "tilt_err_deg": _angle_deg(g_est, g_true),
            "speed_est": float(np.linalg.norm(v_e)), "speed_true": float(np.linalg.norm(v_t)),
            "vz_est": float(v_e[2]), "vz_true": float(v_t[2]),
            "displacement_est_m": float(d_e), "displacement_true_m": float(d_t),
            "bias_accel_est": np.round(f.bias_accel, 3).tolist(),
        }
    return out


def _oracle_start(seq, vio: StereoVio) -> None:
    """Make the estimator's first start the truth's tilt and velocity (a diagnostic: does the
    run diverge without the accelerometer-levelled, at-rest start?)."""
    gt = seq.ground_truth

    def at_rest(t_ns, rotation):
        T = body_poses_at(gt, np.array([t_ns]))[0]
        v = np.array([np.interp(t_ns, gt.t_ns, gt.velocity[:, k]) for k in range(3)])
        return BodyState(t_ns, T[:3, :3], np.zeros(3), v, np.zeros(3), np.zeros(3))

    estimator.BodyState = type("OracleBodyState", (BodyState,),
                               {"at_rest": staticmethod(at_rest)})


def diagnose(folder: str, overrides: list[str], max_frames: int | None, init_s: float,
             oracle: bool = False) -> tuple[dict, list[dict]]:
    seq, _ = read_sequence(folder)
    if "depth0" not in seq.depth or seq.ground_truth is None:
        raise SystemExit(f"{folder}: needs depth0 and ground truth (a simulated folder)")
    cfg = apply_overrides(VioConfig(), overrides) if overrides else VioConfig()
    cam0, cam1 = seq.camera("cam0"), seq.camera("cam1")
    vio = StereoVio(cam0.calibration, cam1.calibration, seq.imu_calibration, seq.imu, cfg)
    estimator.BodyState = BodyState
    if oracle:
        _oracle_start(seq, vio)
    pairs = stereo_pairs(seq)[:max_frames]
    feats, frames = [], []
    with one_blas_thread():
        for t_ns, i, j in pairs:
            tf = vio.track(t_ns, cam0.load(i), cam1.load(j) if j is not None else None,
                           vio.flow_seed())
            feats.append(tf.features)
            frames.append(vio.update(tf))
    t_ns = np.array([p[0] for p in pairs], np.int64)
    gt = seq.ground_truth
    T_WB = body_poses_at(gt, t_ns)
    v_true = np.stack([np.interp(t_ns, gt.t_ns, gt.velocity[:, k]) for k in range(3)], -1)
    truth = match_truth(feats, lambda k: seq.depth["depth0"].load(pairs[k][1]), T_WB,
                        cam0.calibration, cam1.calibration)
    result = VioResult(frames, vio.resets, 0, vio.config, np.zeros(6))
    summ = result.summary(gt)
    cost = np.array([f.cost for f in frames])
    t = (t_ns - t_ns[0]) * 1e-9
    path = float(np.sum(np.linalg.norm(np.diff(T_WB[:, :3, 3], axis=0), axis=1)))
    report = {
        "folder": folder, "frames": len(frames), "keyframes": summ["keyframes"],
        "resets": summ["resets"], "ate_m": summ.get("ate_m"), "path_m": path,
        "speed_mean": float(np.mean(np.linalg.norm(v_true, axis=1))),
        "speed_max": float(np.max(np.linalg.norm(v_true, axis=1))),
        "cost_first_2s": float(np.nanmean(cost[t < 2])),
        "cost_last_2s": float(np.nanmean(cost[t > t[-1] - 2])),
        "mean_tracked": summ["mean_tracked"],
        "mean_stereo": float(np.mean([f.stereo for f in frames])),
        "matches": truth.summary(),
        "init": init_report(frames, T_WB, v_true, init_s),
        "reasons": {r: int(sum(f.reason == r for f in frames))
                    for r in sorted({f.reason for f in frames})},
    }
    # the error growing from the start: the estimate aligned at its first pose
    a = ate(result.trajectory(), gt, alignment="origin")
    drift = dict(zip(a.aligned.t_ns.tolist(), a.errors.tolist(), strict=True))
    rows = []
    for k, f in enumerate(frames):
        rows.append({
            "k": k, "t": round(float(t[k]), 3), "status": f.status, "reason": f.reason,
            "kf": int(f.keyframe), "tracked": f.tracked, "stereo": f.stereo,
            "landmarks": f.landmarks, "cost": round(f.cost, 2), "rows": f.rows,
            "temporal_wrong": round(float(truth.fraction("temporal")[k]), 3),
            "drift_wrong": round(float(truth.fraction("drift")[k]), 3),
            "stereo_wrong": round(float(truth.fraction("stereo")[k]), 3),
            "temporal_n": int(truth.temporal_n[k]), "flow_px": round(
                float(truth.true_flow_median_px[k]), 1),
            "depth_m": round(float(truth.true_depth_median_m[k]), 2),
            "depth_rel": round(float(truth.depth_median_rel[k]), 3),
            "err_origin_m": round(drift.get(f.t_ns, float("nan")), 3),
            "tilt_err_deg": round(_angle_deg(f.rotation[2], T_WB[k, 2, :3]), 2)
            if f.has_pose else float("nan"),
            "speed_est": round(float(np.linalg.norm(f.velocity)), 2),
            "speed_true": round(float(np.linalg.norm(v_true[k])), 2),
        })
    return report, rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="simulated EuRoC folders (with depth0)")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="VioConfig overrides")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--init-s", type=float, default=1.0,
                    help="seconds after the first pose for the second init check [1]")
    ap.add_argument("--oracle-init", action="store_true",
                    help="start from the true tilt and velocity (not levelled, not at rest)")
    ap.add_argument("--csv", default=None, help="per-frame table (one flight)")
    args = ap.parse_args(argv)
    for folder in args.folders:
        report, rows = diagnose(folder, args.set, args.max_frames, args.init_s,
                                args.oracle_init)
        print(json.dumps(report), flush=True)
        if args.csv:
            with open(args.csv, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
