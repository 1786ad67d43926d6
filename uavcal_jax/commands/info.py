"""``uavcal info``: summarise a recording (EuRoC/ASL folder or ROS 1/2 bag)."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from uavcal_jax.argtypes import print_json
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sequence_summary import format_sequence_summary, summarize_sequence
from uavcal_jax.data.timing import CAMERA_GAP_FACTOR, IMU_GAP_FACTOR
from uavcal_jax.errors import DataRepairWarning

DESCRIPTION = f"""\
Summarise a recording: frames per camera, IMU and ground-truth sample counts, nominal
(sensor.yaml) and measured rates, time spans, gaps (IMU intervals longer than
{IMU_GAP_FACTOR:g} periods, camera intervals longer than {CAMERA_GAP_FACTOR:g} periods),
calibration (intrinsics, distortion, resolution, T_BS, IMU noise model), and whether ground
truth, depth and target labels are present. Repairs the reader made (dropped rows or frames)
are listed as warnings. SEQUENCE is an EuRoC/ASL folder (holding mav0, or mav0 itself), a ROS 1
.bag file or a ROS 2 bag folder."""

EPILOG = """\
examples:
  uavcal info ../shared/data/euroc_v101_micro
  uavcal info out/sim --json
  uavcal info flight.bag --imu-topic /imu0 --image-topic /cam0/image_raw"""

def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "info", help="summarise an EuRoC folder or ROS bag", description=DESCRIPTION,
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequence", metavar="SEQUENCE", type=Path,
                        help="EuRoC/ASL folder, ROS 1 .bag file or ROS 2 bag folder")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--strict", action="store_true",
                        help="treat every repair (dropped rows/frames, gaps) as an error")
    parser.add_argument("--imu-topic", default=None, help="bags: IMU topic (default: detect)")
    parser.add_argument("--image-topic", action="append", default=None, dest="image_topics",
                        help="bags: image topic, repeatable (default: every Image topic)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataRepairWarning)
        seq, fmt = read_sequence(args.sequence, strict=args.strict, imu_topic=args.imu_topic,
                                 image_topics=args.image_topics)
    seen = [str(w.message) for w in caught if issubclass(w.category, DataRepairWarning)]
    for w in caught:  # anything else goes on as usual
        if not issubclass(w.category, DataRepairWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    summary = summarize_sequence(seq, fmt, seen)
    if args.json:
        print_json(summary)
    else:
        print(format_sequence_summary(summary))
    return 0
