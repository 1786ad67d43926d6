"""``uavcal vio``: stereo visual-inertial odometry over a recording."""

from __future__ import annotations

import argparse
import csv
import sys
import warnings
from pathlib import Path

import numpy as np

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.commands.info import read_any
from uavcal_jax.data.offset_json import read_offset_json
from uavcal_jax.data.tum import write_tum
from uavcal_jax.errors import DataError, DataRepairWarning

DESCRIPTION = """\
Stereo visual-inertial odometry (RPEOD / VINS-Fusion design: Shi-Tomasi + Lucas-Kanade front
end, IMU preintegration, a sliding window of keyframes solved by Schur-complement
Gauss-Newton with marginalisation) over an EuRoC/ASL folder or a ROS bag with two cameras and
an IMU. Writes the body (IMU) trajectory at camera rate as a TUM file, and beside it
OUT.frames.csv with per-frame flags (status, keyframe, tracked corners, landmarks, reset) and
timings in milliseconds. With ground truth present it reports ATE (SE(3) alignment) and RPE.
Frames without texture, dropped frames and IMU gaps do not stop it: it coasts on the IMU,
flags the frames, and re-initialises."""

EPILOG = """\
examples:
  uavcal vio --sequence ../shared/data/euroc_v101_micro --out traj.txt --plot traj.png
  uavcal vio --sequence out/sim --out traj.txt --offsets offsets.json --json"""

#: Columns of the per-frame CSV written beside the trajectory.
FRAME_COLUMNS = ("t_ns", "status", "reason", "keyframe", "tracked", "stereo", "landmarks",
                 "iterations", "cost", "frontend_ms", "solve_ms", "marginalize_ms", "total_ms")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("vio", help="stereo visual-inertial odometry over a recording",
                              description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", required=True, type=Path, metavar="DIR",
                   help="EuRoC/ASL folder, ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--out", required=True, type=Path, metavar="TRAJ",
                   help="TUM trajectory to write (per-frame flags go to TRAJ.frames.csv)")
    p.add_argument("--offsets", type=Path, default=None, metavar="JSON",
                   help='subtract a constant IMU offset first: a JSON file {"offset": [gx, gy, '
                        'gz, ax, ay, az]} (the calibrator\'s output)')
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="write a PNG of the estimate against the ground truth")
    p.add_argument("--max-frames", type=positive_int, default=None,
                   help="stop after this many stereo frames")
    p.add_argument("--left", default="cam0", help="left camera name [default: cam0]")
    p.add_argument("--right", default="cam1", help="right camera name [default: cam1]")
    p.add_argument("--imu-topic", default=None, help="bags: IMU topic (default: detect)")
    p.add_argument("--image-topic", action="append", default=None, dest="image_topics",
                   help="bags: image topic, repeatable (default: every Image topic)")
    p.add_argument("--json", action="store_true", help="print one JSON summary, no progress bar")
    p.set_defaults(func=run)


def write_frames_csv(path: Path, frames) -> Path:
    """The per-frame flags and timings (:data:`FRAME_COLUMNS`)."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FRAME_COLUMNS)
        for f in frames:
            t = f.timings
            w.writerow([f.t_ns, f.status, f.reason, int(f.keyframe), f.tracked, f.stereo,
                        f.landmarks, f.iterations, f"{f.cost:.6g}",
                        *(f"{t.get(k, 0.0):.3f}" for k in ("frontend", "solve", "marginalize",
                                                          "total"))])
    return path


def summarize(result, ground_truth) -> dict:
    """Counts, timings and, with ground truth, ATE/RPE of a :class:`VioResult`."""
    from uavcal_jax.vio.trajectory_metrics import trajectory_errors

    flags = result.flags()
    times = result.timings()
    traj = result.trajectory()
    out = {
        "frames": len(result.frames), "poses": len(traj), "keyframes": int(flags["keyframe"].sum()),
        "resets": result.resets, "unreadable_frames": result.unreadable,
        "nan_poses": int(sum(not np.all(np.isfinite(f.position)) for f in result.frames
                             if f.has_pose)),
        "mean_tracked": float(np.mean(flags["tracked"])) if len(flags["tracked"]) else 0.0,
        "ms_per_frame": {k: {"mean": float(np.mean(v)) if len(v) else None,
                             "p95": float(np.percentile(v, 95)) if len(v) else None}
                         for k, v in times.items()},
        "imu_offset": result.imu_offset.tolist(),
    }
    if ground_truth is not None and len(traj) >= 3:
        out |= trajectory_errors(traj, ground_truth)
    return out


def run(args) -> int:
    from uavcal_jax.vio.run import run_vio

    if not args.sequence.exists():
        raise DataError(f"{args.sequence}: no such file or folder")
    offset = read_offset_json(args.offsets) if args.offsets is not None else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataRepairWarning)
        sequence, _ = read_any(args.sequence, imu_topic=args.imu_topic,
                               image_topics=args.image_topics)
        result = run_vio(sequence, imu_offset=offset, show_progress=not args.json,
                         max_frames=args.max_frames, left=args.left, right=args.right)
    if not args.json:
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
    traj = result.trajectory()
    if len(traj) == 0:
        raise DataError(f"{args.sequence}: the VIO never initialised (no frame had "
                        f"{result.config.min_init_landmarks} stereo corners)")
    write_tum(args.out, traj)
    frames_csv = write_frames_csv(args.out.with_name(args.out.name + ".frames.csv"),
                                  result.frames)
    gt = sequence.ground_truth
    summary = {"sequence": str(args.sequence), "trajectory": str(args.out),
               "frames_csv": str(frames_csv), **summarize(result, gt)}
    if args.plot is not None:
        if gt is None:
            raise DataError(f"{args.sequence}: --plot needs ground truth, and there is none")
        from uavcal_jax.vio import plot_trajectories

        plot_trajectories(traj, gt, args.plot, title=f"VIO on {sequence.name}",
                          alignment=summary.get("ate_m", {}).get("alignment", "se3"))
        summary["plot"] = str(args.plot)
    if args.json:
        print_json(summary)
        return 0
    ms = summary["ms_per_frame"]["total"]
    print(f"{summary['poses']} poses from {summary['frames']} frames "
          f"({summary['keyframes']} keyframes, {summary['resets']} resets) -> {args.out}")
    if ms["mean"] is not None:
        print(f"time per frame: mean {ms['mean']:.1f} ms, p95 {ms['p95']:.1f} ms")
    if "ate_m" in summary:
        a = summary["ate_m"]
        print(f"ATE rmse {a['rmse']:.4f} m over {a['matched']} poses ({a['alignment']} "
              "alignment)")
    if summary.get("rpe_1m"):
        r = summary["rpe_1m"]
        print(f"RPE over 1 m: {r['translation_rmse_m']:.4f} m, {r['rotation_rmse_deg']:.3f} deg")
    return 0
