"""``uavcal info``: summarise a recording (EuRoC/ASL folder or ROS 1/2 bag)."""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from uavcal_jax.argtypes import print_json
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

MAX_GAPS_LISTED = 50


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


def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml``) or its storage file."""
    if path.is_file():
        return path.suffix in (".bag", ".db3", ".mcap")
    return path.is_dir() and (path / "metadata.yaml").is_file()


def read_any(path: Path, *, strict: bool = False, imu_topic: str | None = None,
             image_topics: list[str] | None = None):
    """Read ``path`` as a bag or an EuRoC folder; returns ``(sequence, format)``."""
    if is_bag(path):
        from uavcal_jax.data.rosbag import read_rosbag

        return read_rosbag(path, imu_topic=imu_topic, image_topics=image_topics,
                           strict=strict), "rosbag"
    from uavcal_jax.data.euroc import read_euroc

    return read_euroc(path, strict=strict), "euroc"


def _finite(value: Any) -> Any:
    """NaN/inf -> None, recursively (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return _finite(value.tolist())
    if isinstance(value, np.generic):
        return _finite(value.item())
    return value


def _span(t_ns: np.ndarray) -> dict[str, Any]:
    if len(t_ns) == 0:
        return {"t_start_ns": None, "t_end_ns": None, "duration_s": 0.0}
    return {"t_start_ns": int(t_ns[0]), "t_end_ns": int(t_ns[-1]),
            "duration_s": (int(t_ns[-1]) - int(t_ns[0])) * 1e-9}


def _timing(t_ns: np.ndarray, nominal_hz: float | None, gap_factor: float) -> dict[str, Any]:
    from uavcal_jax.data.timing import find_gaps, measured_rate_hz, nominal_period_ns

    t_ns = np.asarray(t_ns, dtype=np.int64)
    nominal = nominal_hz if nominal_hz is not None and math.isfinite(nominal_hz) else None
    gaps = find_gaps(t_ns, nominal_period_ns(nominal, t_ns), gap_factor)
    span = _span(t_ns)
    mean_rate = (len(t_ns) - 1) / span["duration_s"] if span["duration_s"] > 0 else None
    return {
        **span,
        "rate_hz_nominal": nominal,
        "rate_hz_measured": measured_rate_hz(t_ns),
        "rate_hz_mean": mean_rate,
        "gap_threshold_periods": gap_factor,
        "n_gaps": len(gaps),
        "gaps": [g.as_dict() for g in gaps[:MAX_GAPS_LISTED]],
    }


def _camera_summary(stream) -> dict[str, Any]:
    cal = stream.calibration
    return {
        "frames": len(stream),
        **_timing(stream.t_ns, cal.rate_hz, CAMERA_GAP_FACTOR),
        "calibration": {
            "camera_model": cal.camera_model,
            "resolution": list(cal.resolution),
            "intrinsics": np.asarray(cal.intrinsics).tolist(),
            "distortion_model": cal.distortion_model,
            "distortion": np.asarray(cal.distortion).tolist(),
            "T_BS": np.asarray(cal.T_BS).tolist(),
        },
    }


def summarize(sequence, fmt: str = "euroc", warnings_seen: list[str] | None = None
              ) -> dict[str, Any]:
    """A JSON-ready summary of a :class:`~uavcal_jax.data.sequence.Sequence`."""
    out: dict[str, Any] = {
        "sequence": sequence.name,
        "path": str(sequence.root) if sequence.root is not None else None,
        "format": fmt,
        "cameras": {name: _camera_summary(s) for name, s in sequence.cameras.items()},
        "depth": {name: _camera_summary(s) for name, s in sequence.depth.items()},
    }
    if sequence.imu is not None:
        cal = sequence.imu_calibration
        imu: dict[str, Any] = {
            "samples": len(sequence.imu),
            **_timing(sequence.imu.t_ns, cal.rate_hz if cal else None, IMU_GAP_FACTOR),
            "calibration": None,
        }
        if cal is not None:
            from uavcal_jax.data.yaml_io import imu_noise_to_yaml

            # the noise model under the sensor.yaml key names the recording states it with
            imu["calibration"] = {"T_BS": np.asarray(cal.T_BS).tolist(),
                                  **imu_noise_to_yaml(cal.noise)}
        out["imu"] = imu
    else:
        out["imu"] = None
    gt = sequence.ground_truth
    if gt is not None:
        gt_out: dict[str, Any] = {"present": True, "states": len(gt), **_span(gt.t_ns)}
        from uavcal_jax.data.timing import measured_rate_hz

        gt_out["rate_hz_measured"] = measured_rate_hz(gt.t_ns)
        if gt.bias_gyro is not None and len(gt):
            gt_out["bias_gyro_mean"] = gt.bias_gyro.mean(axis=0).tolist()
            gt_out["bias_accel_mean"] = gt.bias_accel.mean(axis=0).tolist()
        out["ground_truth"] = gt_out
    else:
        out["ground_truth"] = {"present": False, "states": 0}
    tg = sequence.targets
    out["targets"] = ({"present": True, "rows": len(tg), "classes": list(tg.class_names),
                       "tracks": int(np.unique(tg.track_id).size)}
                      if tg is not None else {"present": False})
    spans = [v for v in ([s["t_start_ns"], s["t_end_ns"]] for s in
                         [*out["cameras"].values(), *( [out["imu"]] if out["imu"] else [])])
             if v[0] is not None]
    if spans:
        t0, t1 = min(s[0] for s in spans), max(s[1] for s in spans)
        out["t_start_ns"], out["t_end_ns"], out["duration_s"] = t0, t1, (t1 - t0) * 1e-9
    out["warnings"] = list(warnings_seen or [])
    return _finite(out)


def _fmt_rate(x: float | None) -> str:
    return "?" if x is None else f"{x:.3f}".rstrip("0").rstrip(".")


def _fmt_gaps(block: dict[str, Any]) -> str:
    if not block["n_gaps"]:
        return "no gaps"
    worst = max(g["duration_s"] for g in block["gaps"])
    return f"{block['n_gaps']} gaps (longest {worst * 1e3:.1f} ms)"


def format_text(s: dict[str, Any]) -> str:
    lines = [f"{s['sequence']}  ({s['format']}, {s['path']})"]
    if "duration_s" in s:
        lines.append(f"  span: {s['duration_s']:.3f} s  "
                     f"[{s['t_start_ns'] * 1e-9:.6f} .. {s['t_end_ns'] * 1e-9:.6f}]")
    for kind in ("cameras", "depth"):
        for name, c in s[kind].items():
            cal = c["calibration"]
            w, h = cal["resolution"]
            lines.append(
                f"  {name}: {c['frames']} frames, {c['duration_s']:.3f} s, "
                f"{_fmt_rate(c['rate_hz_nominal'])} Hz nominal / "
                f"{_fmt_rate(c['rate_hz_measured'])} Hz measured, {_fmt_gaps(c)}")
            intr = cal["intrinsics"]
            intr_text = ("unknown" if any(v is None for v in intr)
                         else ", ".join(f"{v:g}" for v in intr))
            lines.append(f"      {w}x{h} {cal['camera_model']}, fu fv cu cv = {intr_text}; "
                         f"{cal['distortion_model']} "
                         f"[{', '.join(f'{v:g}' for v in cal['distortion'])}]")
            lines.append(f"      T_BS translation [m] = "
                         f"[{', '.join(f'{row[3]:.4f}' for row in cal['T_BS'][:3])}]")
    imu = s["imu"]
    if imu:
        lines.append(f"  imu0: {imu['samples']} samples, {imu['duration_s']:.3f} s, "
                     f"{_fmt_rate(imu['rate_hz_nominal'])} Hz nominal / "
                     f"{_fmt_rate(imu['rate_hz_measured'])} Hz measured, {_fmt_gaps(imu)}")
        cal = imu["calibration"]
        if cal:
            lines.append(
                f"      noise: gyro {cal['gyroscope_noise_density']:g} rad/s/sqrt(Hz), "
                f"walk {cal['gyroscope_random_walk']:g}; accel "
                f"{cal['accelerometer_noise_density']:g} m/s^2/sqrt(Hz), "
                f"walk {cal['accelerometer_random_walk']:g}")
    else:
        lines.append("  imu: none")
    gt = s["ground_truth"]
    if gt["present"]:
        lines.append(f"  ground truth: {gt['states']} states, {gt['duration_s']:.3f} s, "
                     f"{_fmt_rate(gt['rate_hz_measured'])} Hz")
        if "bias_gyro_mean" in gt:
            lines.append("      mean bias gyro ["
                         + ", ".join(f"{v:.5f}" for v in gt["bias_gyro_mean"])
                         + "] rad/s, accel ["
                         + ", ".join(f"{v:.4f}" for v in gt["bias_accel_mean"]) + "] m/s^2")
    else:
        lines.append("  ground truth: none")
    tg = s["targets"]
    if tg["present"]:
        lines.append(f"  targets: {tg['rows']} labels, {tg['tracks']} tracks, "
                     f"classes {', '.join(tg['classes'])}")
    for w in s["warnings"]:
        lines.append(f"  warning: {w}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataRepairWarning)
        seq, fmt = read_any(args.sequence, strict=args.strict, imu_topic=args.imu_topic,
                            image_topics=args.image_topics)
    seen = [str(w.message) for w in caught if issubclass(w.category, DataRepairWarning)]
    for w in caught:  # anything else goes on as usual
        if not issubclass(w.category, DataRepairWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    summary = summarize(seq, fmt, seen)
    if args.json:
        print_json(summary)
    else:
        print(format_text(summary))
    return 0
