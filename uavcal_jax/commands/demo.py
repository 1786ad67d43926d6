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

from uavcal_jax.argtypes import print_json

#: The demo flight: a few seconds of procedural flight at half EuRoC resolution.
DEMO_DURATION_S = 3.0
DEMO_RESOLUTION = (376, 240)


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
                       seed=ctx["args"].seed, batch_size=10)
    report = simulate_report(config, ctx["out"], progress=ctx["progress"])
    ctx["root"] = report.root
    return {"out": str(report.root), **report.resolved["counts"],
            "config": report.resolved["config"]}


def _read(ctx: dict[str, Any]) -> dict[str, Any]:
    from uavcal_jax.commands.info import summarize
    from uavcal_jax.data import read_euroc

    seq = read_euroc(ctx["root"], strict=True)  # the simulator's output needs no repairs
    ctx["sequence"] = seq
    return summarize(seq)


def _show_summary(result: dict[str, Any]) -> str:
    from uavcal_jax.commands.info import format_text

    return format_text(result)


#: The demo's steps, in order.
STEPS: list[DemoStep] = [
    DemoStep("simulate", f"simulate a {DEMO_DURATION_S:g} s procedural flight "
             f"({DEMO_RESOLUTION[0]}x{DEMO_RESOLUTION[1]} stereo, IMU, depth, targets)",
             _simulate),
    DemoStep("read", "read it back as an EuRoC ASL folder", _read, _show_summary),
]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the pipeline on a short simulated flight (no data needed)",
        description="Simulate a short procedural flight into a temporary folder (or --keep "
        "DIR), read it back as an EuRoC ASL recording and print its summary: counts, rates, "
        "duration, target labels and calibration.")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="write the simulated recording to DIR (DIR/mav0) and keep it; DIR must "
                        "not exist or be empty [default: a temporary folder, deleted]")
    p.add_argument("--seed", type=int, default=0, help="seed of the flight and scene "
                   "[default: 0]")
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
