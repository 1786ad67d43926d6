"""``uavcal simulate``: simulate a flight and write it as an EuRoC ASL folder."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from uavcal_jax.argtypes import parse_resolution, positive, positive_int, print_json
from uavcal_jax.errors import DataError

DESCRIPTION = """\
Simulate a flight and write it as an EuRoC ASL folder: DIR/mav0 with cam0 and cam1 (EuRoC's
VI-sensor intrinsics, radial-tangential distortion and extrinsics; frames rendered at
T_WC = T_WB(t) @ T_BS), depth0/depth1 (uint16 PNG, z-depth in millimetres, 0 = none), imu0
(200 Hz, EuRoC's ADIS16448 noise model), state_groundtruth_estimate0 (17 columns: position,
quaternion w,x,y,z, velocity, the IMU's true gyro and accel biases) and target0 (per frame and
camera: boxes of the targets' visible pixels and their 3D world positions). The resolved
configuration is written to DIR/sim_config.json. Read the result with `uavcal info DIR`.

The flight is a TUM trajectory file (--trajectory) or a procedural flight from --seed. The
same options and seed give byte-identical files. The output is written to a temporary folder
beside DIR and renamed at the end: a folder named DIR is always complete."""

EPILOG = """\
examples:
  uavcal simulate --out out/sim --duration 20 --seed 3
  uavcal simulate --out out/v101 --trajectory V1_01_easy.txt --start 10 --duration 30
  uavcal simulate --out out/imu_only --no-frames --no-imu-noise --duration 60"""


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that build a :class:`~uavcal_jax.sim.simulate.SimConfig` (shared with
    other commands that simulate)."""
    g = parser.add_argument_group("flight")
    g.add_argument("--trajectory", metavar="FILE",
                   help="TUM trajectory to fly (lines 't tx ty tz qx qy qz qw', t in seconds; "
                        "e.g. a EuRoC ground truth). The output keeps the file's own "
                        "timestamps. Default: a procedural flight (hover, turns, climbs, "
                        "straight legs) generated from --seed.")
    g.add_argument("--start", type=float, default=None, metavar="S",
                   help="with --trajectory: start S seconds after the file's first timestamp "
                        "(relative, not the file's absolute clock) [default: 0]")
    g.add_argument("--duration", type=positive, default=10.0, metavar="S",
                   help="seconds of flight to simulate [default: 10]; with --trajectory, "
                        "--start + --duration must lie within the file")
    g.add_argument("--seed", type=int, default=0,
                   help="seeds the procedural flight, the IMU noise and biases, and the scene "
                        "[default: 0]")
    g = parser.add_argument_group("sensors")
    g.add_argument("--resolution", type=parse_resolution, default=(752, 480), metavar="WxH",
                   help="frame size; other than EuRoC's 752x480 the intrinsics are scaled "
                        "(same field of view) [default: 752x480]")
    g.add_argument("--color", choices=("gray", "rgb"), default="gray",
                   help="8-bit gray frames (like EuRoC) or RGB [default: gray]")
    g.add_argument("--camera-rate", type=positive, default=20.0, metavar="HZ",
                   help="frame rate of cam0/cam1 [default: 20]")
    g.add_argument("--imu-rate", type=positive, default=200.0, metavar="HZ",
                   help="IMU and ground-truth rate [default: 200]")
    g.add_argument("--no-imu-noise", action="store_true",
                   help="exact IMU: no white noise, no bias (default: EuRoC ADIS16448 noise "
                        "densities, bias random walks and turn-on biases; the true biases are "
                        "in the ground truth)")
    g.add_argument("--no-frames", action="store_true",
                   help="write only the IMU and the ground truth (no cameras, depth, labels)")
    g.add_argument("--no-depth", action="store_true", help="do not write depth0/depth1")
    g.add_argument("--no-targets", action="store_true", help="do not write target0 labels")


def config_from_args(args: argparse.Namespace):
    """A :class:`~uavcal_jax.sim.simulate.SimConfig` from :func:`add_sim_arguments`' options."""
    from uavcal_jax.sim.simulate import SimConfig

    if args.start is not None and args.trajectory is None:
        raise DataError("--start needs --trajectory (a procedural flight has no file clock)")
    if args.start is not None and args.start < 0:
        raise DataError(f"--start must be >= 0 seconds, got {args.start:g}", args.trajectory)
    return SimConfig(
        trajectory=args.trajectory,
        start=0.0 if args.start is None else float(args.start),
        duration=float(args.duration),
        resolution=tuple(args.resolution),
        color=args.color,
        seed=int(args.seed),
        imu_noise=not args.no_imu_noise,
        frames=not args.no_frames,
        depth=not args.no_depth,
        targets=not args.no_targets,
        camera_rate_hz=float(args.camera_rate),
        imu_rate_hz=float(args.imu_rate),
        batch_size=int(getattr(args, "batch", 8)),
        png_workers=int(getattr(args, "workers", 2)),
    )


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate a flight into an EuRoC ASL folder (IMU, stereo, depth, "
        "target labels, ground truth)", description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="output folder (gets DIR/mav0 and DIR/sim_config.json); must not exist "
                        "or be empty unless --overwrite")
    p.add_argument("--overwrite", action="store_true",
                   help="replace DIR if it holds a previous simulation")
    add_sim_arguments(p)
    g = p.add_argument_group("speed (do not change the output)")
    g.add_argument("--batch", type=positive_int, default=8, metavar="N",
                   help="frames rendered per compiled call [default: 8]")
    g.add_argument("--workers", type=positive_int, default=2, metavar="N",
                   help="threads encoding PNGs while the next batch renders [default: 2]")
    p.add_argument("--json", action="store_true",
                   help="print one JSON summary line and no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from uavcal_jax.sim.simulate import simulate_report

    config = config_from_args(args)
    try:
        config.validate()
    except ValueError as err:
        raise DataError(str(err)) from None
    t0 = time.perf_counter()
    report = simulate_report(config, args.out, progress=not args.json, overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    counts = report.resolved["counts"]
    summary = {"out": str(report.root), "seconds": round(seconds, 3), **counts,
               "t_start_ns": report.resolved["flight"]["t_start_ns"],
               "t_end_ns": report.resolved["flight"]["t_end_ns"],
               "timings": {k: round(v, 3) for k, v in report.timings.items()}}
    if args.json:
        print_json(summary)
    else:
        frames = f", {counts['frames']} stereo pairs" if "frames" in counts else ""
        labels = f", {counts['target_rows']} target labels" if counts.get("target_rows") else ""
        print(f"wrote {report.root}: {counts['imu']} IMU samples{frames}{labels} "
              f"in {seconds:.1f} s")
    return 0
