"""``uavcal vio``: stereo visual-inertial odometry over a recording."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.config import apply_overrides, read_config, write_config
from uavcal_jax.data.offset_json import read_offset_json
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.tum import write_tum
from uavcal_jax.data.vio_frames import write_frames_csv
from uavcal_jax.errors import DataError, DataRepairWarning

DESCRIPTION = """\
Stereo visual-inertial odometry (RPEOD / VINS-Fusion design: Shi-Tomasi + Lucas-Kanade front
end, IMU preintegration, a sliding window of keyframes solved by Schur-complement
Gauss-Newton with marginalisation) over an EuRoC/ASL folder or a ROS bag with two cameras and
an IMU. Writes the body (IMU) trajectory at camera rate as a TUM file, and beside it
OUT.frames.csv with per-frame flags (status, keyframe, tracked corners, landmarks, reset) and
timings in milliseconds, and OUT.config.json: the resolved settings (the camera-dependent ones
from the recording's calibration) and the command's inputs, which --config reads back to
repeat the run. With ground truth present it reports ATE (SE(3) alignment) and RPE.
Frames without texture, dropped frames and IMU gaps do not stop it: it coasts on the IMU,
flags the frames, and re-initialises."""

EPILOG = """\
examples:
  uavcal vio --sequence ../shared/data/euroc_v101_micro --out traj.txt --plot traj.png
  uavcal vio --sequence out/sim --out traj.txt --offsets offsets.json --json
  uavcal vio --sequence out/sim --out t2.txt --set solver.max_iterations=4 frontend.equalize=clahe
  uavcal vio --sequence out/sim --out t3.txt --config traj.txt.config.json   # repeat a run

--set keys are the fields of uavcal_jax/vio/config.py's VioConfig tree (section.field; the
file gives each default and its meaning); an unknown key's error lists the valid ones."""

#: The top-level key of OUT.config.json holding the command's inputs beside the settings.
INPUTS_KEY = "inputs"
# inputs a --config file supplies when the command line does not give them, and their
# defaults when neither does
_RESTORED = {"imu_offset": None, "max_frames": None, "left": "cam0", "right": "cam1",
             "imu_topic": None, "image_topics": None}


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("vio", help="stereo visual-inertial odometry over a recording",
                              description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", required=True, type=Path, metavar="DIR",
                   help="EuRoC/ASL folder, ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--out", required=True, type=Path, metavar="TRAJ",
                   help="TUM trajectory to write (per-frame flags go to TRAJ.frames.csv, the "
                        "resolved settings to TRAJ.config.json)")
    p.add_argument("--offsets", type=Path, default=None, metavar="JSON",
                   help='subtract a constant IMU offset first: a JSON file {"offset": [gx, gy, '
                        'gz, ax, ay, az]} (the calibrator\'s output)')
    p.add_argument("--config", type=Path, default=None, metavar="JSON",
                   help="start from the settings of an earlier run's TRAJ.config.json (before "
                        "--set); its recorded IMU offset, --max-frames, cameras and topics "
                        "apply unless given here")
    p.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                   dest="overrides", help="set a setting (keys below); repeatable")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="write a PNG of the estimate against the ground truth")
    p.add_argument("--max-frames", type=positive_int, default=None,
                   help="stop after this many stereo frames")
    p.add_argument("--left", default=None, help="left camera name [default: cam0]")
    p.add_argument("--right", default=None, help="right camera name [default: cam1]")
    p.add_argument("--imu-topic", default=None, help="bags: IMU topic (default: detect)")
    p.add_argument("--image-topic", action="append", default=None, dest="image_topics",
                   help="bags: image topic, repeatable (default: every Image topic)")
    p.add_argument("--json", action="store_true", help="print one JSON summary, no progress bar")
    p.set_defaults(func=run)


def _settings(args) -> tuple:
    """The run's :class:`VioConfig` (``--config``'s, or the defaults, then ``--set``) and its
    inputs (the command line's, else ``--config``'s recorded ones, else the defaults)."""
    from uavcal_jax.vio.config import VioConfig

    config, recorded = VioConfig(), {}
    if args.config is not None:
        config = read_config(args.config, VioConfig, ignore=(INPUTS_KEY,))
        recorded = _recorded_inputs(args.config)
    config = apply_overrides(config, args.overrides)
    inputs = {}
    for key, default in _RESTORED.items():
        given = getattr(args, key, None)
        inputs[key] = given if given is not None else recorded.get(key, default)
    if args.offsets is not None:
        inputs["imu_offset"] = read_offset_json(args.offsets).tolist()
    return config, inputs


def _recorded_inputs(path: Path) -> dict:
    import json

    inputs = json.loads(path.read_text()).get(INPUTS_KEY, {})
    if not isinstance(inputs, dict):
        raise DataError(f"{INPUTS_KEY!r} is not a JSON object", path)
    return {k: v for k, v in inputs.items() if k in _RESTORED}


def run(args) -> int:
    from uavcal_jax.data.imu_coverage import check_imu_covers
    from uavcal_jax.vio.run import run_vio

    if not args.sequence.exists():
        raise DataError(f"{args.sequence}: no such file or folder")
    config, inputs = _settings(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataRepairWarning)
        sequence, _ = read_sequence(args.sequence, imu_topic=inputs["imu_topic"],
                                    image_topics=inputs["image_topics"])
        check_imu_covers(sequence, inputs["left"], max_frames=inputs["max_frames"])
        result = run_vio(sequence, config, imu_offset=inputs["imu_offset"],
                         show_progress=not args.json, max_frames=inputs["max_frames"],
                         left=inputs["left"], right=inputs["right"])
    if not args.json:
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
    traj = result.trajectory()
    if len(traj) == 0:
        raise DataError(f"{args.sequence}: the VIO never initialised (no frame had "
                        f"{result.config.min_init_landmarks} stereo corners)")
    write_tum(args.out, traj)
    frames_csv = write_frames_csv(args.out.with_name(args.out.name + ".frames.csv"),
                                  result.frame_rows())
    config_json = write_config(
        args.out.with_name(args.out.name + ".config.json"), result.config,
        **{INPUTS_KEY: {"sequence": str(args.sequence), "out": str(args.out),
                        "offsets_file": None if args.offsets is None else str(args.offsets),
                        "config_file": None if args.config is None else str(args.config),
                        "overrides": list(args.overrides), **inputs}})
    gt = sequence.ground_truth
    summary = {"sequence": str(args.sequence), "trajectory": str(args.out),
               "frames_csv": str(frames_csv), "config": str(config_json),
               **result.summary(gt)}
    if args.plot is not None:
        if gt is None:
            raise DataError(f"{args.sequence}: --plot needs ground truth, and there is none")
        from uavcal_jax.plots import plot_trajectories

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
