"""``uavcal run``: calibrate the IMU, fly on the VIO, find, locate and follow the target."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from uavcal_jax.argtypes import print_json
from uavcal_jax.config import apply_overrides
from uavcal_jax.errors import DataError, DataRepairWarning

DESCRIPTION = """\
The whole job over one recording (an EuRoC/ASL folder, real or simulated, or a ROS bag with an
IMU and a stereo pair), read once: (0) check that the IMU covers every frame; (1) the IMU
offset: by default (offset.method=vio-bias) the stereo VIO runs on the recorded IMU and the
offset is read from its own bias states (one VIO pass; reported, not removed); another
method (--set offset.method=visual-ls|self-calib|transformer, `uavcal calib predict`'s) runs
first and its estimate is removed, as is --offsets FILE's; --no-offset removes none; (2) run
the stereo VIO while (3) the detector runs on the left camera in a second thread (every frame,
or every k-th: --set detect.every=K); (4) an online tracker, frame by frame as on the drone,
follows the track of the class seen longest so far, locates each of its boxes in the world
(from the depth image, or from stereo disparity when the recording has none) and filters it
(constant-velocity Kalman filter); (5) and computes follow set-points: a fixed distance and
height from the target, facing it, speed and yaw-rate limited.

OUT receives, under these names:
  trajectory.txt        the VIO trajectory (TUM: t x y z qx qy qz qw; body = IMU frame)
  targets.csv           t_ns,track_id,class,x,y,z,var_x,var_y,var_z,confidence,kind: one row per
                        frame and estimate, kind raw (one frame's localisation) or filtered;
                        world frame of the trajectory
  setpoints.csv         t_ns,x,y,z,yaw: one row per left frame
  metrics.json          ate_m, offset {estimate, true, method}, target_error_m {raw, filtered:
                        median, rmse, max}, follow, ms_per_frame (steady state, per stage) and
                        compile_s; what needs a truth the recording lacks is null, with the
                        reason under "omitted"
  config.json           the resolved settings and the inputs
  top_view.png, frames.png, localisation_error.png
Errors against the truth are computed after aligning the trajectory to the ground truth (the
same transform applied to the target and set-points)."""

EPILOG = """\
examples:
  uavcal simulate --trajectory traj.txt --duration 20 --follow-targets 1 --out sim
  uavcal run --sequence sim --out run1
  uavcal run --sequence sim --out run2 --detector labels --no-offset --json
  uavcal run --sequence ../shared/data/euroc_v101_micro --out run3 --detector runs/det
  uavcal run --sequence sim --out run4 --set detect.every=2 follow.distance=5 filter.accel_psd=2
  uavcal run --sequence sim --out run5 --set offset.method=visual-ls offset.visual_ls.every=2

--detector: a `uavcal detect train` run folder (its best weights); default the weights shipped
in the package; `labels`: the recording's own target labels (simulated recordings), a perfect
detector for measuring the rest of the pipeline.
--set keys are the fields of uavcal_jax/pipeline/run_config.py's RunConfig tree (offset.method,
offset.<method>.* with the method's `uavcal calib predict --set` keys: offset.vio_bias.*,
offset.visual_ls.*, offset.self_calib.*, offset.transformer.{checkpoint,kind,frame_dtype};
vio.* is the one VIO setting of the run and of its offset method; detect.*, associate.*,
locate.*, stereo.*, filter.*, heading.*, follow.*, warmup_frames; the stages' own config
classes give each default and its meaning); an unknown key's error lists the valid ones."""

#: ``--detector`` value that uses the recording's target labels.
LABELS = "labels"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("run", help="calibrate, VIO, detect, locate and follow a target "
                              "over a recording", description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", required=True, type=Path, metavar="DIR",
                   help="EuRoC/ASL folder, ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--out", required=True, type=Path, metavar="OUT",
                   help="output folder (created; files named as above are replaced)")
    offset = p.add_mutually_exclusive_group()
    offset.add_argument("--offsets", type=Path, default=None, metavar="FILE",
                        help='remove this IMU offset instead of estimating one: a JSON file '
                             '{"offset": [gx, gy, gz, ax, ay, az]} (uavcal calib predict\'s '
                             'output)')
    offset.add_argument("--no-offset", action="store_true",
                        help="remove no IMU offset (offset.method=none)")
    p.add_argument("--detector", default=None, metavar="RUN",
                   help="a `uavcal detect train` run folder, or 'labels' [default: the "
                        "shipped weights]")
    p.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                   dest="overrides", help="set a setting (keys below); repeatable")
    p.add_argument("--json", action="store_true",
                   help="print metrics.json (one line), no progress bars")
    p.set_defaults(func=run)


def _detector(args, config, sequence):
    from uavcal_jax.pipeline.detectors import LabelDetector, load_network_detector

    if args.detector != LABELS:
        return load_network_detector(args.detector, config.detect.detector_threshold(),
                                     config.detect.tile_config())
    if sequence.targets is None:
        raise DataError("--detector labels needs target labels (mav0/target0), and the "
                        "recording has none", args.sequence)
    return LabelDetector(sequence.targets)


def run(args) -> int:
    from uavcal_jax.data.offset_json import read_offset_json
    from uavcal_jax.pipeline.run_config import NO_OFFSET, RunConfig

    if not args.sequence.exists():
        raise DataError("no such file or folder", args.sequence)
    config = apply_overrides(RunConfig(), args.overrides)
    if args.no_offset:
        config = apply_overrides(config, {"offset.method": NO_OFFSET})
    offsets = read_offset_json(args.offsets) if args.offsets is not None else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataRepairWarning)
        from uavcal_jax.data.imu_coverage import check_imu_covers
        from uavcal_jax.data.read import read_sequence
        from uavcal_jax.pipeline.run import run_pipeline
        from uavcal_jax.pipeline.run_outputs import format_run_summary
        from uavcal_jax.plots import plot_run

        read = read_sequence(args.sequence)  # once: the detector and the run share it
        check_imu_covers(read[0])  # before the detector is loaded (the run checks it too)
        detector = _detector(args, config, read[0])
        result = run_pipeline(
            args.sequence, args.out, config, read=read, offsets=offsets, detector=detector,
            progress=not args.json,
            inputs={"offsets_file": None if args.offsets is None else str(args.offsets),
                    "detector_option": args.detector, "overrides": list(args.overrides)})
        figures = plot_run(result)
    if not args.json:
        for message in dict.fromkeys(str(w.message) for w in caught):
            print(f"warning: {message}", file=sys.stderr)
        for note in result.notes:
            print(f"warning: {note}", file=sys.stderr)
    if args.json:
        print_json(json.loads(result.paths["metrics"].read_text()))
        return 0
    print(format_run_summary(result.metrics, result.out_dir, figures))
    return 0
