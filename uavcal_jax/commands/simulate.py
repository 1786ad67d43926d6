"""``uavcal simulate``: simulate a flight and write it as an EuRoC ASL folder."""

from __future__ import annotations

import argparse
import sys
import textwrap
import time
import warnings
from pathlib import Path

from uavcal_jax.argtypes import (
    parse_offset,
    parse_resolution,
    parse_vector3,
    positive,
    positive_int,
    print_json,
)
from uavcal_jax.config import apply_overrides, valid_keys
from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.data.euroc_rig import EUROC_RESOLUTION
from uavcal_jax.errors import DataError, DataRepairWarning, FlightLimitWarning
from uavcal_jax.sim.config import BODY_FRAMES, COLORS, SimConfig

#: The option defaults, from :class:`SimConfig` (one place for each).
_D = SimConfig()

DESCRIPTION = f"""\
Simulate a flight and write it as an EuRoC ASL folder: DIR/mav0 with cam0 and cam1 (EuRoC's
VI-sensor intrinsics, radial-tangential distortion and extrinsics; frames rendered at
T_WC = T_WB(t) @ T_BS), depth0/depth1 (uint16 PNG, z-depth in millimetres, 0 = none), imu0
({_D.imu_rate_hz:g} Hz, EuRoC's ADIS16448 noise model), {fmt.GROUND_TRUTH_FOLDER}
({fmt.GROUND_TRUTH_FIELDS} columns: position, quaternion w,x,y,z, velocity, the IMU's true gyro
and accel biases) and target0 (per frame and camera: boxes of the targets' visible pixels and
their 3D world positions). The resolved configuration (the options, then any --set) is written
to DIR/sim_config.json. Read the result with `uavcal info DIR`.

The flight is a TUM trajectory file (--trajectory) or a procedural flight from --seed. A file's
poses are fitted with smoothing matched to the noise measured on them (irregular intervals,
near-duplicate stamps, gaps and position steps are handled); sim_config.json records the fit's
residual and the flight's peak specific force and angular rate (flight.trajectory_fit). A
flight beyond what a drone flies is simulated with a one-line warning; one no airframe could
fly (a broken file) is refused (the limits: uavcal_jax.sim.trajectory_fit.FitConfig). Frames
image like EuRoC's MT9V034 (exposure x gain calibrated to the real V1_01 frames' brightness,
shot and read noise measured on them, motion blur over the exposure) unless --ideal-camera. The
same options and seed give byte-identical files. The output is written to a temporary folder
beside DIR and renamed at the end: a folder named DIR is always complete."""

EPILOG = """\
examples:
  uavcal simulate --out out/sim --duration 20 --seed 3
  uavcal simulate --out out/v101 --trajectory V1_01_easy.txt --start 10 --duration 30
  uavcal simulate --out out/imu_only --no-frames --no-imu-noise --duration 60
  uavcal simulate --out out/miscal --imu-offset=-0.02,0.01,0.03,0.2,-0.1,0.15
  uavcal simulate --out out/fast --set imu_rate_hz=400 blur_samples=1
  uavcal simulate --out out/fpv --trajectory indoor_forward_3.txt --body-frame flu \\
      --camera-pitch 30 --follow-targets 1 --duration 8

--set keys (SimConfig fields):
{keys}"""


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that build a :class:`~uavcal_jax.sim.config.SimConfig`; every default is
    the dataclass field's."""
    g = parser.add_argument_group("flight")
    g.add_argument("--trajectory", metavar="FILE", default=_D.trajectory,
                   help="TUM trajectory to fly (lines 't tx ty tz qx qy qz qw', t in seconds; "
                        "e.g. a EuRoC ground truth). The output keeps the file's own "
                        "timestamps. Default: a procedural flight (hover, turns, climbs, "
                        "straight legs) generated from --seed.")
    # None (not given) so that --start without --trajectory can be refused
    g.add_argument("--start", type=float, default=None, metavar="S",
                   help="with --trajectory: start S seconds after the file's first timestamp "
                        f"(relative, not the file's absolute clock) [default: {_D.start:g}]")
    g.add_argument("--duration", type=positive, default=_D.duration, metavar="S",
                   help=f"seconds of flight to simulate [default: {_D.duration:g}]; with "
                        "--trajectory, --start + --duration must lie within the file")
    g.add_argument("--body-frame", choices=BODY_FRAMES, default=_D.body_frame,
                   help="the trajectory file's body convention: 'euroc' (EuRoC's IMU frame, x "
                        "up, z forward) or 'flu' (x forward, y left, z up: UZH-FPV, most "
                        "motion-capture rigs; EuRoC's IMU and cameras are mounted on it as on "
                        "EuRoC's MAV) [default: %(default)s]")
    g.add_argument("--follow-targets", type=int, default=_D.follow_targets, metavar="N",
                   help="place N moving targets (car, person, alternating) on the floor where "
                        "cam0 looks along the flight; each moves, stops and turns and stays in "
                        "view most of the time; they are track ids 0..N-1 of the labels, "
                        "their world tracks in target0/track.csv [default: %(default)s]")
    g.add_argument("--seed", type=int, default=_D.seed,
                   help="seeds the procedural flight, the IMU noise and biases, and the scene "
                        f"[default: {_D.seed}]")
    g = parser.add_argument_group("sensors")
    w, h = _D.resolution
    g.add_argument("--resolution", type=parse_resolution, default=_D.resolution, metavar="WxH",
                   help="frame size; other than EuRoC's {}x{} the intrinsics are scaled (same "
                        "field of view) [default: {}x{}]".format(*EUROC_RESOLUTION, w, h))
    g.add_argument("--color", choices=COLORS, default=_D.color,
                   help=f"8-bit gray frames (like EuRoC) or RGB [default: {_D.color}]")
    g.add_argument("--camera-pitch", type=float, default=_D.camera_pitch_deg, metavar="DEG",
                   help="pitch of the stereo rig below the drone's forward axis: 0 looks "
                        "forward, 45 as UZH-FPV's 45-degree flights, 90 straight down; the "
                        "cameras' T_BS in sensor.yaml are the pitched ones [default: EuRoC's "
                        "rig, cam0 19.8 degrees below forward]")
    g.add_argument("--imu-rotation", type=parse_vector3, default=_D.imu_rotation_deg,
                   metavar="RX,RY,RZ",
                   help="turn the IMU on the airframe by this rotation vector (degrees, in the "
                        "IMU frame it had): the same flight and frames, the IMU and the ground "
                        "truth in the turned frame, sensor.yaml's T_BS to match (another "
                        "drone's mounting, e.g. 0,-90,0 puts gravity on z) [default: none]")
    g.add_argument("--camera-rate", type=positive, default=_D.camera_rate_hz, metavar="HZ",
                   help=f"frame rate of cam0/cam1 [default: {_D.camera_rate_hz:g}]")
    g.add_argument("--imu-rate", type=positive, default=_D.imu_rate_hz, metavar="HZ",
                   help=f"IMU and ground-truth rate [default: {_D.imu_rate_hz:g}]")
    g.add_argument("--no-imu-noise", dest="imu_noise", action="store_false",
                   default=_D.imu_noise,
                   help="exact IMU: no white noise, no bias (default: EuRoC ADIS16448 noise "
                        "densities, bias random walks and turn-on biases; the true biases are "
                        "in the ground truth)")
    g.add_argument("--imu-offset", type=parse_offset, default=_D.imu_offset,
                   metavar="GX,GY,GZ,AX,AY,AZ",
                   help="add this constant offset (gyro rad/s xyz, accel m/s^2 xyz) to the "
                        "written IMU after its noise and biases: a miscalibrated recording. "
                        "It is recorded in sim_config.json; the ground truth's biases stay the "
                        "IMU's true ones. Write --imu-offset=-0.02,... when the first value is "
                        "negative [default: none]")
    g.add_argument("--no-frames", dest="frames", action="store_false", default=_D.frames,
                   help="write only the IMU and the ground truth (no cameras, depth, labels)")
    g.add_argument("--no-depth", dest="depth", action="store_false", default=_D.depth,
                   help="do not write depth0/depth1")
    g.add_argument("--no-targets", dest="targets", action="store_false", default=_D.targets,
                   help="do not write target0 labels")
    g = parser.add_argument_group(
        "camera (EuRoC's MT9V034: exposure x gain, shot and read noise, 8-bit quantisation, "
        "motion blur over the exposure)")
    g.add_argument("--ideal-camera", action="store_true", default=_D.ideal_camera,
                   help="write the noise-free, sharp rendered image instead (no exposure, "
                        "noise or blur; the options below are ignored)")
    g.add_argument("--exposure", type=positive, default=_D.exposure_ms, metavar="MS",
                   help="exposure time, milliseconds (EuRoC's auto-exposure: about 1-10 ms "
                        f"indoors) [default: {_D.exposure_ms:g}]")
    g.add_argument("--gain", type=positive, default=_D.gain,
                   help="analog gain: brightness and noise scale with it "
                        f"[default: {_D.gain:g}]")
    g.add_argument("--no-sensor-noise", dest="sensor_noise", action="store_false",
                   default=_D.sensor_noise, help="no shot or read noise (exposure, gain, "
                   "quantisation and blur stay)")
    g.add_argument("--blur-samples", type=positive_int, default=_D.blur_samples, metavar="N",
                   help="sub-exposures averaged for motion blur, 1 = none "
                        f"[default: {_D.blur_samples}]")
    g = parser.add_argument_group("speed (do not change the output)")
    g.add_argument("--batch", type=positive_int, default=_D.batch_size, metavar="N",
                   help=f"frames rendered per compiled call [default: {_D.batch_size}]")
    g.add_argument("--workers", type=positive_int, default=_D.png_workers, metavar="N",
                   help="threads encoding PNGs while the next batch renders "
                        f"[default: {_D.png_workers}]")
    parser.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                        help="set SimConfig fields (keys below), applied after the options "
                             "above; repeatable; an unknown key is an error naming it")


def config_from_args(args: argparse.Namespace) -> SimConfig:
    """A :class:`~uavcal_jax.sim.config.SimConfig` from :func:`add_sim_arguments`' options,
    then its ``--set key=value`` overrides (:func:`uavcal_jax.config.apply_overrides`).

    Raises:
        DataError: ``--start`` without ``--trajectory`` or below zero; an unknown ``--set``
            key (named, with the valid ones) or a value that does not parse.
    """
    if args.start is not None and args.trajectory is None \
            and getattr(args, "imu_from", None) is None:
        raise DataError("--start needs --trajectory or --imu-from (a procedural flight has no "
                        "file clock)")
    if args.start is not None and args.start < 0:
        raise DataError(f"--start must be >= 0 seconds, got {args.start:g}", args.trajectory)
    config = SimConfig(
        trajectory=args.trajectory,
        start=_D.start if args.start is None else float(args.start),
        duration=float(args.duration),
        body_frame=args.body_frame,
        camera_pitch_deg=args.camera_pitch,
        imu_rotation_deg=args.imu_rotation,
        resolution=tuple(args.resolution),
        color=args.color,
        seed=int(args.seed),
        imu_noise=args.imu_noise,
        imu_offset=args.imu_offset,
        frames=args.frames,
        depth=args.depth,
        targets=args.targets,
        follow_targets=int(args.follow_targets),
        camera_rate_hz=float(args.camera_rate),
        imu_rate_hz=float(args.imu_rate),
        ideal_camera=bool(args.ideal_camera),
        exposure_ms=float(args.exposure),
        gain=float(args.gain),
        sensor_noise=bool(args.sensor_noise),
        blur_samples=int(args.blur_samples),
        batch_size=int(args.batch),
        png_workers=int(args.workers),
    )
    return apply_overrides(config, args.set)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate a flight into an EuRoC ASL folder (IMU, stereo, depth, "
        "target labels, ground truth)", description=DESCRIPTION,
        epilog=EPILOG.format(keys=textwrap.fill(", ".join(valid_keys(SimConfig)), 88,
                                                initial_indent="  ", subsequent_indent="  ")),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="output folder (gets DIR/mav0 and DIR/sim_config.json); must not exist "
                        "or be empty unless --overwrite")
    p.add_argument("--overwrite", action="store_true",
                   help="replace DIR if it holds a previous simulation")
    add_sim_arguments(p)
    p.add_argument("--imu-from", type=Path, default=None, metavar="DIR",
                   help="hybrid recording: keep the real IMU and ground truth of the EuRoC/ASL "
                        "folder (or bag) DIR, rows copied exactly, over --start (seconds after "
                        "its first IMU sample) and --duration, and render the cameras along its "
                        "ground truth on its camera clock (uavcal_jax.sim.hybrid). The IMU noise "
                        "is the real sensor's (--no-imu-noise does not apply); --imu-offset is "
                        "added to the real samples. Excludes --trajectory")
    p.add_argument("--json", action="store_true",
                   help="print one JSON summary line and no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from uavcal_jax.sim.simulate import simulate_report  # JAX and the renderer: only to run

    config = config_from_args(args)
    try:
        config.validate()
    except ValueError as err:
        raise DataError(str(err)) from None
    t0 = time.perf_counter()
    notes: list[str] = []
    shown = (FlightLimitWarning, DataRepairWarning)
    with warnings.catch_warnings():
        for category in shown:
            warnings.simplefilter("always", category)
        warnings.showwarning = _one_line(warnings.showwarning, shown, notes)
        if args.imu_from is not None:
            if args.trajectory is not None:
                raise DataError("--imu-from flies the real recording's ground truth; drop "
                                "--trajectory")
            from uavcal_jax.sim.hybrid import simulate_hybrid

            report = simulate_hybrid(args.imu_from, args.out, config, progress=not args.json,
                                     overwrite=args.overwrite)
        else:
            report = simulate_report(config, args.out, progress=not args.json,
                                     overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    counts = report.resolved["counts"]
    flight = report.resolved["flight"]
    summary = {"out": str(report.root), "seconds": round(seconds, 3), **counts,
               "t_start_ns": flight["t_start_ns"], "t_end_ns": flight["t_end_ns"],
               "imu_offset": report.resolved["config"]["imu_offset"],
               "timings": {k: round(v, 3) for k, v in report.timings.items()},
               "warnings": notes}
    if "trajectory_fit" in flight:
        summary["trajectory_fit"] = flight["trajectory_fit"]
    if args.json:
        print_json(summary)
    else:
        frames = f", {counts['frames']} stereo pairs" if "frames" in counts else ""
        labels = f", {counts['target_rows']} target labels" if counts.get("target_rows") else ""
        offset = ("" if config.imu_offset is None else
                  " (IMU offset " + ",".join(f"{v:g}" for v in config.imu_offset) + ")")
        print(f"wrote {report.root}: {counts['imu']} IMU samples{offset}{frames}{labels} "
              f"in {seconds:.1f} s")
    return 0


def _one_line(show, categories: tuple[type[Warning], ...], notes: list[str]):
    """A ``warnings.showwarning`` that prints ``categories`` as one ``warning: ...`` line on
    stderr as they happen (a flight-limit warning comes before minutes of rendering) and keeps
    their text in ``notes``; other warnings go to ``show`` as usual."""

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, categories):
            notes.append(str(message))
            print(f"warning: {message}", file=sys.stderr, flush=True)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning
