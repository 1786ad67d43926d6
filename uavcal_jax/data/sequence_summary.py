"""A recording's summary: counts, rates, spans, gaps and calibration of every sensor.

:func:`summarize_sequence` turns a :class:`~uavcal_jax.data.sequence.Sequence` into a
JSON-ready dict (what ``uavcal info --json`` prints); :func:`format_sequence_summary` into
text. Gaps are IMU intervals longer than :data:`~uavcal_jax.data.timing.IMU_GAP_FACTOR`
nominal periods and camera intervals longer than
:data:`~uavcal_jax.data.timing.CAMERA_GAP_FACTOR` periods; times are int64 nanoseconds and
float seconds.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.data.timing import (
    CAMERA_GAP_FACTOR,
    IMU_GAP_FACTOR,
    find_gaps,
    measured_rate_hz,
    nominal_period_ns,
)
from uavcal_jax.data.yaml_io import imu_noise_to_yaml

#: Gaps listed per stream (all are counted).
MAX_GAPS_LISTED = 50


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


def summarize_sequence(sequence: Sequence, fmt: str = "euroc",
                       warnings_seen: list[str] | None = None) -> dict[str, Any]:
    """A JSON-ready summary of ``sequence`` (what ``uavcal info`` prints).

    Args:
        sequence: the recording.
        fmt: its format (``read_sequence``'s second value), recorded as ``format``.
        warnings_seen: the repairs the reader made, recorded as ``warnings``.

    Returns:
        ``sequence``, ``path``, ``format``; per camera (and depth stream) its frame count,
        time span (``t_start_ns``, ``t_end_ns``, ``duration_s``), nominal/measured/mean rates
        in Hz, gaps (at most :data:`MAX_GAPS_LISTED` listed) and calibration; the same for
        ``imu`` (``None`` without one) with its noise model; ``ground_truth`` and ``targets``
        (``present`` and counts); the whole span; ``warnings``. NaN/inf become ``None``.
    """
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
            # the noise model under the sensor.yaml key names the recording states it with
            imu["calibration"] = {"T_BS": np.asarray(cal.T_BS).tolist(),
                                  **imu_noise_to_yaml(cal.noise)}
        out["imu"] = imu
    else:
        out["imu"] = None
    gt = sequence.ground_truth
    if gt is not None:
        gt_out: dict[str, Any] = {"present": True, "states": len(gt), **_span(gt.t_ns)}
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


def format_sequence_summary(s: dict[str, Any]) -> str:
    """The human-readable text of :func:`summarize_sequence`'s result (several lines)."""
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
