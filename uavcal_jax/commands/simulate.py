"""``uavcal simulate``: simulate a flight and write it as an EuRoC ASL folder."""

from __future__ import annotations

import argparse
import sys
import textwrap
import time
import warnings
from pathlib import Path

from uavcal_jax.argtypes import (
    ConfigFlag,
    add_config_flags,
    flag_overrides,
    parse_offset,
    parse_resolution,
    parse_vector3,
    positive,
    positive_int,
    print_json,
)
from uavcal_jax.config import apply_overrides, valid_keys
from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.errors import DataError, DataRepairWarning, FlightLimitWarning
from uavcal_jax.sim.config import BODY_FRAMES, COLORS, IDEAL_SENSORS, SimConfig

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
shot and read noise measured on them, motion blur over the exposure) unless --ideal-camera.
EuRoC's rig is the default: the cameras' auto-exposure and vignetting, the IMU's rotor
vibration (V1_01's spectrum), scale factors, axis misalignment and g-sensitivity
(uavcal_jax.sim.config: EUROC_CAMERA_PRESET, EUROC_IMU_REALISM); --ideal-sensors turns every
one off. The same options and seed give byte-identical files. The output is written to a
temporary folder beside DIR and renamed at the end: a folder named DIR is always complete."""

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


#: The options, by group: each an alias of ``--set FIELD=VALUE`` whose help and default are
#: the :class:`SimConfig` field's.
SIM_FLAGS: dict[str, tuple[ConfigFlag, ...]] = {
    "flight": (
        ConfigFlag("trajectory", metavar="FILE",
                   note="The output keeps the file's own timestamps (e.g. a EuRoC ground "
                        "truth).", default_text="a procedural flight from --seed"),
        ConfigFlag("start", type=float, metavar="S",
                   note="Needs --trajectory or --imu-from."),
        ConfigFlag("duration", type=positive, metavar="S",
                   note="With --trajectory, --start + --duration must lie within the file."),
        ConfigFlag("body_frame", choices=BODY_FRAMES),
        ConfigFlag("follow_targets", metavar="N"),
        ConfigFlag("seed"),
    ),
    "sensors": (
        ConfigFlag("resolution", type=parse_resolution, metavar="WxH"),
        ConfigFlag("color", choices=COLORS),
        ConfigFlag("camera_pitch_deg", flag="--camera-pitch", type=float, metavar="DEG",
                   default_text="EuRoC's rig, cam0 19.8 degrees below forward"),
        ConfigFlag("imu_rotation_deg", flag="--imu-rotation", type=parse_vector3,
                   metavar="RX,RY,RZ", note="E.g. 0,-90,0 puts gravity on z; write "
                   "--imu-rotation=-90,... when the first value is negative."),
        ConfigFlag("camera_rate_hz", flag="--camera-rate", type=positive, metavar="HZ"),
        ConfigFlag("imu_rate_hz", flag="--imu-rate", type=positive, metavar="HZ"),
        ConfigFlag("imu_noise"),
        ConfigFlag("imu_offset", type=parse_offset, metavar="GX,GY,GZ,AX,AY,AZ",
                   note="Write --imu-offset=-0.02,... when the first value is negative."),
        ConfigFlag("frames"),
        ConfigFlag("depth"),
        ConfigFlag("targets"),
    ),
    "camera (EuRoC's MT9V034: exposure x gain, shot and read noise, 8-bit quantisation, "
    "motion blur over the exposure)": (
        ConfigFlag("ideal_camera"),
        ConfigFlag("exposure_ms", flag="--exposure", type=positive, metavar="MS"),
        ConfigFlag("gain", type=positive),
        ConfigFlag("sensor_noise"),
        ConfigFlag("blur_samples", type=positive_int, metavar="N"),
    ),
    "speed (do not change the output)": (
        ConfigFlag("batch_size", flag="--batch", type=positive_int, metavar="N"),
        ConfigFlag("png_workers", flag="--workers", type=positive_int, metavar="N"),
    ),
}
_ALL_FLAGS = tuple(f for group in SIM_FLAGS.values() for f in group)


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that build a :class:`~uavcal_jax.sim.config.SimConfig` (:data:`SIM_FLAGS`),
    then ``--set``."""
    for title, flags in SIM_FLAGS.items():
        add_config_flags(parser.add_argument_group(title), SimConfig, flags)
    parser.add_argument("--ideal-sensors", action="store_true",
                        help="turn off every realism effect of EuRoC's rig (auto-exposure, "
                             "vignetting, rotor vibration, IMU scale, misalignment and "
                             "g-sensitivity: sim.config's IDEAL_SENSORS), before the options "
                             "above and --set")
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
    options = flag_overrides(args, _ALL_FLAGS)
    if "start" in options and options.get("trajectory") is None \
            and getattr(args, "imu_from", None) is None:
        raise DataError("--start needs --trajectory or --imu-from (a procedural flight has no "
                        "file clock)")
    if options.get("start", 0.0) < 0:
        raise DataError(f"--start must be >= 0 seconds, got {options['start']:g}",
                        options.get("trajectory"))
    base = SimConfig(**IDEAL_SENSORS) if getattr(args, "ideal_sensors", False) else SimConfig()
    return apply_overrides(apply_overrides(base, options), args.set)


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
            if config.trajectory is not None:
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
