"""``uavcal demo``: the main job on built-in defaults, no external data.

A short procedural flight past a moving target is simulated with a physical-range IMU offset;
``uavcal run``'s pipeline (:func:`uavcal_jax.pipeline.run.run_pipeline`) flies it in one VIO
pass: the stereo VIO on the recorded IMU, whose bias states are the default offset estimate,
the shipped detector beside it, the target located, filtered and followed; then the other
estimators of ``uavcal calib predict`` estimate the offset without ground truth, beside the
run's. Everything is printed against the simulator's truth.

The demo is a list of :class:`DemoStep`; each step reads and extends a shared context dict
and returns a JSON-able result.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from uavcal_jax.argtypes import parse_offset, print_json
from uavcal_jax.config import (
    ConfigError,
    UnknownConfigKey,
    apply_overrides,
    to_dict,
    valid_keys,
)
from uavcal_jax.errors import DataError
from uavcal_jax.sim.config import LOW_RESOLUTION, SimConfig

#: The demo flight: seconds of procedural flight at the simulator's low resolution
#: (:data:`uavcal_jax.sim.config.LOW_RESOLUTION`), with one moving target (a car) placed where
#: the camera looks.
DEMO_DURATION_S = 12.0
DEMO_FOLLOW_TARGETS = 1
#: The flight's seed: one that moves from the start and turns (121 degrees of yaw). The VIO
#: adds keyframes only with parallax, so a hover adds no information (seed 0's flight turns on
#: the spot for its first 9 s), and the accelerometer's bias across gravity is told from the
#: tilt only by turning.
DEMO_SEED = 9
#: The constant offset the demo's IMU carries (gyro rad/s xyz, accel m/s^2 xyz): in the range
#: of real MEMS biases (EuRoC's: ~0.08 rad/s, ~0.16 m/s^2). The simulated sensor adds its own
#: turn-on bias (with seed 9 about (-0.048, -0.025, -0.015, -0.083, -0.077, 0.001)); these
#: signs keep every channel's total error away from zero (its smallest, 0.028 rad/s and
#: 0.099 m/s^2), so that "better than no correction" means something on each.
DEMO_IMU_OFFSET = (0.02, -0.015, -0.02, -0.08, -0.06, -0.1)


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


#: The demo's simulation (``--set sim.KEY=VALUE`` changes it).
DEMO_SIM = SimConfig(duration=DEMO_DURATION_S, resolution=LOW_RESOLUTION, seed=DEMO_SEED,
                     batch_size=10, imu_offset=DEMO_IMU_OFFSET,
                     follow_targets=DEMO_FOLLOW_TARGETS)
#: The two config trees ``--set`` reaches: ``sim.*`` (:class:`SimConfig`) and ``run.*``
#: (:class:`~uavcal_jax.pipeline.run_config.RunConfig`), resolved into ``demo_config.json``.
DEMO_TREES = ("sim", "run")
#: Written in the output folder: the resolved ``{"sim": ..., "run": ..., "overrides": ...}``.
DEMO_CONFIG = "demo_config.json"


def demo_configs(overrides: list[str], seed: int | None = None,
                 imu_offset: tuple[float, ...] | None = None) -> dict[str, Any]:
    """``{"sim": SimConfig, "run": RunConfig}``: :data:`DEMO_SIM` and ``RunConfig()`` with
    ``--seed`` and ``--imu-offset`` (``None``: not given), then ``overrides``
    (``sim.KEY=VALUE``, ``run.KEY=VALUE``) applied.

    Raises:
        ConfigError: an override outside the two trees, an unknown key (named, with the valid
            ones) or a bad value.
    """
    from uavcal_jax.pipeline.run_config import RunConfig

    sim = DEMO_SIM if seed is None else dataclasses.replace(DEMO_SIM, seed=seed)
    if imu_offset is not None:
        sim = dataclasses.replace(sim, imu_offset=imu_offset)
    configs: dict[str, Any] = {"sim": sim, "run": RunConfig()}
    for tree, config in configs.items():
        prefix = tree + "."
        mine = [o[len(prefix):] for o in overrides if o.startswith(prefix)]
        try:
            configs[tree] = apply_overrides(config, mine)
        except UnknownConfigKey as err:
            raise UnknownConfigKey(prefix + err.key,
                                   [prefix + k for k in valid_keys(config)]) from None
    stray = [o for o in overrides if not o.startswith(tuple(t + "." for t in DEMO_TREES))]
    if stray:
        raise ConfigError(f"--set {stray[0]!r}: demo keys start with sim. (the simulation) or "
                          "run. (uavcal run's settings)")
    try:
        configs["sim"].validate()
    except ValueError as err:
        raise ConfigError(f"sim: {err}") from None
    return configs


def _simulate(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.sim.simulate import simulate_report

    report = simulate_report(ctx["config"]["sim"], ctx["out"] / "recording",
                             progress=ctx["progress"])
    ctx["root"] = report.root
    return {"out": str(report.root), **report.resolved["counts"],
            "config": report.resolved["config"]}


def _read(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.data.read import read_sequence
    from uavcal_jax.data.sequence_summary import summarize_sequence

    # the simulator's output needs no repairs
    seq, fmt = read_sequence(ctx["root"], strict=True)
    ctx["sequence"], ctx["format"] = seq, fmt
    return summarize_sequence(seq, fmt)


def _show_summary(result: dict[str, Any]) -> str:
    from uavcal_jax.data.sequence_summary import format_sequence_summary

    return format_sequence_summary(result)


#: The offset estimators the demo compares (``uavcal calib predict --method``); the run's own
#: method's estimate is the run's (for the default, vio-bias, read from its one VIO pass).
DEMO_METHODS = ("vio-bias", "visual-ls", "transformer")


def _calibrate(ctx: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from uavcal_jax.data.true_offset import true_offset
    from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS
    from uavcal_jax.pipeline.predict_offset import predict_offset, score

    seq = ctx["sequence"]
    injected = ctx["config"]["sim"].imu_offset
    injected = None if injected is None else np.asarray(injected)
    # the constant to subtract: the injected offset plus the simulated IMU's own bias
    true = true_offset("total", injected, seq.ground_truth)
    run = ctx["run_offset"]  # the run's estimate, scored by the run under its label and span
    methods = {}
    for method in DEMO_METHODS:
        if method == run["method"]:
            offset = np.asarray(run["estimate"], np.float64)
            methods[method] = {"offset": offset.tolist(), "channels": list(SIX_CHANNELS),
                               "label": run["label"], "true": run["true"].tolist(),
                               "error": (offset - run["true"]).tolist()}
            continue
        summary, estimate = predict_offset(seq, method, progress=ctx["progress"])
        # each against the truth under its own label and span, over all six channels
        scored = score(estimate, injected, seq.ground_truth, all_channels=True)
        methods[method] = {"offset": estimate.offset.tolist(),
                           "channels": list(estimate.channels), "label": summary["label"],
                           "true": scored["true"], "error": scored["error"]}
    return {"channels": list(SIX_CHANNELS), "injected":
            None if injected is None else injected.tolist(), "true": true.tolist(),
            "no_correction_error": (-true).tolist(), "methods": methods,
            "run_method": run["method"], "removed_by_run": bool(run["removed"])}


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
        "gyro only, transformer: the shipped small weights; "
        + (f"the run removed {result['run_method']}'s estimate before its VIO)"
           if result["removed_by_run"] else
           f"{result['run_method']}: read from the run's own VIO pass, on the recorded IMU)")])


def _run(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.pipeline.run import run_pipeline
    from uavcal_jax.plots import plot_run

    result = run_pipeline(ctx["root"], ctx["out"] / "run", ctx["config"]["run"],
                          read=(ctx["sequence"], ctx["format"]), progress=ctx["progress"],
                          inputs={"command": "uavcal demo"})
    ctx["run_offset"] = result.offset
    figures = plot_run(result)
    return {"metrics": result.metrics, "out": str(result.out_dir),
            "figures": {k: str(v) for k, v in figures.items()}}


def _show_run(result: dict[str, Any]) -> str:
    from uavcal_jax.pipeline.run_outputs import format_run_summary

    return "\n".join("      " + line for line in format_run_summary(
        result["metrics"], result["out"], result["figures"]).splitlines())


#: The demo's steps, in order.
STEPS: list[DemoStep] = [
    DemoStep("simulate", f"simulate a {DEMO_SIM.duration:g} s procedural flight past a moving "
             f"car ({DEMO_SIM.resolution[0]}x{DEMO_SIM.resolution[1]} stereo, IMU with a "
             "constant offset, depth, target labels)", _simulate),
    DemoStep("read", "read it back as an EuRoC ASL folder", _read, _show_summary),
    DemoStep("run", "uavcal run, one VIO pass: the VIO on the recorded IMU (its bias states "
             "are the offset estimate), the shipped detector beside it, the car located, "
             "filtered and followed", _run, _show_run),
    DemoStep("calibrate", "the IMU's constant error without ground truth: the run's VIO bias "
             "beside the visual gyro least squares and the transformer (shipped weights)",
             _calibrate, _show_offsets),
]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="the main job on a short simulated flight (no data needed)",
        description="Simulate a short procedural flight past a moving car, whose IMU carries a "
        "constant offset; run `uavcal run`'s pipeline on the flight in one VIO pass: the "
        "stereo VIO on the recorded IMU, whose bias states are the default offset estimate, "
        "the shipped detector on every left frame beside it, the car located from the depth "
        "images, filtered and followed; then estimate the offset without ground truth with the "
        "other estimators of `uavcal calib predict` (the visual gyro least squares, the "
        "transformer with its shipped weights), printed beside the run's against the truth "
        "(the offset plus the simulated sensor's own bias) and against no correction. Prints "
        "the ATE, the target's localisation error, the follow figures, the time per frame in "
        "steady state, the offsets, and the output folder (the recording, and uavcal run's "
        "files and figures).")
    p.add_argument("--out", type=Path, metavar="DIR", default=None,
                   help="write everything under DIR (DIR/recording, DIR/run); DIR must not "
                        "exist or be empty [default: a new folder in the temporary directory]")
    p.add_argument("--seed", type=int, default=None, help="seed of the flight and scene "
                   f"(sim.seed) [default: {DEMO_SEED}]")
    p.add_argument("--imu-offset", type=parse_offset, default=None,
                   metavar="GX,GY,GZ,AX,AY,AZ",
                   help="constant offset the simulated IMU carries, which the calibrate step "
                        "estimates (write --imu-offset=-0.01,... for a negative first value) "
                        "(sim.imu_offset) [default: "
                        + ",".join(f"{v:g}" for v in DEMO_IMU_OFFSET) + "]")
    p.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                   dest="overrides",
                   help="sim.KEY=VALUE sets a field of the simulation (the keys of `uavcal "
                        "simulate --help`'s --set; the demo's: duration "
                        f"{DEMO_SIM.duration:g}, resolution {DEMO_SIM.resolution[0]}x"
                        f"{DEMO_SIM.resolution[1]}, follow_targets {DEMO_SIM.follow_targets}, "
                        f"batch_size {DEMO_SIM.batch_size}), run.KEY=VALUE one of `uavcal "
                        "run`'s settings (its --set keys), e.g. --set sim.seed=3 "
                        "run.detect.every=2; applied after --seed and --imu-offset;"
                        f" the resolved trees go to DIR/{DEMO_CONFIG}")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (uavcal run's metrics.json plus out, "
                        "step_seconds and the other steps' results) and no progress")
    p.set_defaults(func=run)


def run_steps(args: argparse.Namespace, configs: dict[str, Any], out: Path, *, progress: bool,
              log: Callable[[str], None]) -> dict[str, Any]:
    """Run :data:`STEPS` with ``configs`` (:func:`demo_configs`), writing under ``out``;
    returns ``{step name: result}`` and ``seconds`` per step."""
    ctx: dict[str, Any] = {"args": args, "config": configs, "out": out, "progress": progress}
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


def _output_folder(out: Path | None) -> Path:
    if out is None:
        return Path(tempfile.mkdtemp(prefix="uavcal-demo-"))
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DataError("--out must be a new or empty folder (the demo does not overwrite)",
                        out)
    out.mkdir(parents=True, exist_ok=True)
    return out


def run(args: argparse.Namespace) -> int:
    def log(text: str) -> None:
        if not args.json:
            print(text, flush=True)

    configs = demo_configs(args.overrides, args.seed, args.imu_offset)
    out = _output_folder(args.out)
    (out / DEMO_CONFIG).write_text(json.dumps(
        {"sim": configs["sim"].to_dict(), "run": to_dict(configs["run"]),
         "overrides": list(args.overrides)}, indent=2) + "\n")
    t0 = time.perf_counter()
    results = run_steps(args, configs, out, progress=not args.json, log=log)
    total = time.perf_counter() - t0
    if args.json:
        run_result = results.pop("run")
        seconds = results.pop("seconds")
        print_json({**run_result["metrics"], "out": str(out),
                    "step_seconds": {**seconds, "total": round(total, 3)}, "steps": results})
    else:
        print(f"demo done in {total:.0f} s; everything is in {out}")
    return 0
