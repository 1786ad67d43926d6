"""``uavcal demo``: the whole pipeline on built-in defaults, no external data.

The demo is a list of :class:`DemoStep`; each step reads and extends a shared context dict
and returns a JSON-able result. Later issues append steps (calibrate the IMU, run the VIO,
detect and follow a target) to :data:`STEPS`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from uavcal_jax.argtypes import parse_offset, print_json

#: The demo flight: a few seconds of procedural flight at half EuRoC resolution.
DEMO_DURATION_S = 3.0
DEMO_RESOLUTION = (376, 240)
#: The constant offset the demo's IMU carries (gyro rad/s xyz, accel m/s^2 xyz): a
#: miscalibration in the range of real MEMS biases (EuRoC's: ~0.08 rad/s, ~0.16 m/s^2).
DEMO_IMU_OFFSET = (0.02, -0.015, 0.01, 0.08, -0.06, 0.1)


@dataclass(frozen=True)
class DemoStep:
    """One step of the demo.

    Attributes:
        name: short name, printed and used as the key of its result.
        title: one line saying what it does.
        run: ``run(ctx) -> result``; ``ctx`` holds ``args``, ``out`` (the recording's
            folder), ``progress`` and what earlier steps stored; ``result`` is a JSON-able
            dict.
        show: ``show(result) -> str``, the human-readable text of the result ("" for none).
    """

    name: str
    title: str
    run: Callable[[dict[str, Any]], dict[str, Any]]
    show: Callable[[dict[str, Any]], str] = lambda result: ""


def _simulate(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.sim.config import SimConfig
    from uavcal_jax.sim.simulate import simulate_report

    config = SimConfig(duration=DEMO_DURATION_S, resolution=DEMO_RESOLUTION,
                       seed=ctx["args"].seed, batch_size=10, imu_offset=ctx["args"].imu_offset)
    report = simulate_report(config, ctx["out"], progress=ctx["progress"])
    ctx["root"] = report.root
    return {"out": str(report.root), **report.resolved["counts"],
            "config": report.resolved["config"]}


def _read(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.data.read import read_sequence
    from uavcal_jax.data.sequence_summary import summarize_sequence

    # the simulator's output needs no repairs
    seq, fmt = read_sequence(ctx["root"], strict=True)
    ctx["sequence"] = seq
    return summarize_sequence(seq, fmt)


def _show_summary(result: dict[str, Any]) -> str:
    from uavcal_jax.data.sequence_summary import format_sequence_summary

    return format_sequence_summary(result)


#: The offset estimators the demo compares (``uavcal calib predict --method``); the first is
#: the default method, whose estimate the VIO step removes.
DEMO_METHODS = ("vio-bias", "visual-ls", "transformer")


def _calibrate(ctx: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from uavcal_jax.data.true_offset import true_offset
    from uavcal_jax.pipeline.offset_estimators import DEFAULT_METHOD
    from uavcal_jax.pipeline.predict_offset import predict_offset

    seq = ctx["sequence"]
    injected = None if ctx["args"].imu_offset is None else np.asarray(ctx["args"].imu_offset)
    # the constant to subtract: the injected offset plus the simulated IMU's own bias
    true = true_offset("total", injected, seq.ground_truth)
    methods, estimates = {}, {}
    for method in DEMO_METHODS:
        summary, estimate = predict_offset(ctx["root"], method, progress=ctx["progress"])
        estimates[method] = estimate.offset
        methods[method] = {"offset": estimate.offset.tolist(),
                           "channels": list(estimate.channels), "label": summary["label"],
                           "error": (estimate.offset - true).tolist()}
    ctx["offset_estimate"] = estimates[DEFAULT_METHOD]
    ctx["offset_method"] = DEFAULT_METHOD
    return {"channels": ["gx", "gy", "gz", "ax", "ay", "az"], "injected":
            None if injected is None else injected.tolist(), "true": true.tolist(),
            "no_correction_error": (-true).tolist(), "methods": methods,
            "removed_by_vio_step": DEFAULT_METHOD}


def _show_offsets(result: dict[str, Any]) -> str:
    def row(name: str, values) -> str:
        return f"      {name:>22}" + "".join(f"{v:>9.4f}" for v in values)

    rows = [f"      {'':>22}" + "".join(f"{c:>9}" for c in result["channels"]),
            row("true (offset + bias)", result["true"]),
            row("no correction: error", result["no_correction_error"])]
    for name, m in result["methods"].items():
        rows.append(row(f"{name}: error", m["error"]))
    return "\n".join(rows + [
        "      (gyro rad/s, accel m/s^2; the truth is the injected offset plus the simulated "
        "IMU's own bias, from the ground truth, which no method reads; visual-ls estimates the "
        "gyro only, transformer: the shipped small weights; the VIO step removes "
        f"{result['removed_by_vio_step']}'s estimate)"])


def _vio(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.vio.run import run_vio

    seq = ctx["sequence"]
    result = run_vio(seq, imu_offset=ctx.get("offset_estimate"), show_progress=ctx["progress"])
    out = result.summary(seq.ground_truth)
    out["offset_removed"] = (f"the calibrate step's {ctx['offset_method']} estimate"
                             if "offset_estimate" in ctx else None)
    return out


def _show_vio(result: dict[str, Any]) -> str:
    ms = result["ms_per_frame"]["total"]
    text = (f"      {result['poses']} poses from {result['frames']} stereo frames, "
            f"{result['keyframes']} keyframes, {result['resets']} resets")
    if ms["mean"] is not None:
        text += f"\n      time per frame: mean {ms['mean']:.1f} ms (the first frames compile)"
    if "ate_m" in result:
        text += (f"\n      ATE rmse {result['ate_m']['rmse']:.3f} m against the ground truth "
                 f"({result['ate_m']['alignment']} alignment)")
    return text


#: The demo's steps, in order.
STEPS: list[DemoStep] = [
    DemoStep("simulate", f"simulate a {DEMO_DURATION_S:g} s procedural flight "
             f"({DEMO_RESOLUTION[0]}x{DEMO_RESOLUTION[1]} stereo, IMU, depth, targets)",
             _simulate),
    DemoStep("read", "read it back as an EuRoC ASL folder", _read, _show_summary),
    DemoStep("calibrate", "estimate the IMU's constant error without ground truth: the VIO's "
             "bias, the visual gyro least squares and the transformer (shipped weights)",
             _calibrate, _show_offsets),
    DemoStep("vio", "stereo visual-inertial odometry on the flight, the estimated offset "
             "removed", _vio, _show_vio),
]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the pipeline on a short simulated flight (no data needed)",
        description="Simulate a short procedural flight whose IMU carries a constant offset "
        "into a temporary folder (or --keep DIR), read it back as an EuRoC ASL recording, "
        "print its summary (counts, rates, duration, target labels, calibration), "
        "estimate the IMU's constant error with the estimators of `uavcal calib predict` (the "
        "VIO's bias, the visual gyro least squares, the transformer with its shipped weights), "
        "printed against the true one (the offset plus the simulated sensor's own bias), and "
        "run the stereo VIO with the default method's estimate removed, printing its ATE and "
        "time per frame.")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="write the simulated recording to DIR (DIR/mav0) and keep it; DIR must "
                        "not exist or be empty [default: a temporary folder, deleted]")
    p.add_argument("--seed", type=int, default=0, help="seed of the flight and scene "
                   "[default: 0]")
    p.add_argument("--imu-offset", type=parse_offset, default=DEMO_IMU_OFFSET,
                   metavar="GX,GY,GZ,AX,AY,AZ",
                   help="constant offset the simulated IMU carries, which the calibrate step "
                        "estimates (write --imu-offset=-0.01,... for a negative first value) "
                        "[default: " + ",".join(f"{v:g}" for v in DEMO_IMU_OFFSET) + "]")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (each step's result) and no progress")
    p.set_defaults(func=run)


def run_steps(args: argparse.Namespace, out: Path, *, progress: bool,
              log: Callable[[str], None]) -> dict[str, Any]:
    """Run :data:`STEPS`, simulating into ``out``; returns ``{step name: result}`` and
    ``seconds`` per step."""
    ctx: dict[str, Any] = {"args": args, "out": out, "progress": progress}
    results: dict[str, Any] = {}
    seconds: dict[str, float] = {}
    for i, step in enumerate(STEPS, start=1):
        log(f"[{i}/{len(STEPS)}] {step.name}: {step.title}")
        t0 = time.perf_counter()
        results[step.name] = step.run(ctx)
        seconds[step.name] = round(time.perf_counter() - t0, 3)
        text = step.show(results[step.name])
        log(f"      done in {seconds[step.name]:.1f} s" + (f"\n{text}" if text else ""))
    results["seconds"] = seconds
    return results


def run(args: argparse.Namespace) -> int:
    def log(text: str) -> None:
        if not args.json:
            print(text, flush=True)

    if args.keep is not None:
        results = run_steps(args, args.keep, progress=not args.json, log=log)
    else:
        with tempfile.TemporaryDirectory(prefix="uavcal-demo-") as tmp:
            results = run_steps(args, Path(tmp) / "sim", progress=not args.json, log=log)
            results["simulate"]["out"] = None  # deleted with the temporary folder
    if args.json:
        print_json(results)
    elif args.keep is not None:
        print(f"kept the recording in {results['simulate']['out']}")
    return 0
