"""Benchmark the simulator: EuRoC-like output (stereo gray frames, IMU, depth, target labels).

The issue's goal: 60 s of flight -- 1,200 stereo pairs at 752x480 plus 200 Hz IMU, depth and
target labels -- in at most 3 minutes on a 2-core CPU. This script simulates into a temporary
folder (deleted afterwards unless ``--keep DIR``) and reports the wall time of each stage:

* ``trajectory_imu``: flight generation, IMU synthesis and ground truth;
* ``compile``: scene building and compiling the frame renderer (once per configuration);
* ``render``: time spent waiting for JAX renders (what encoding did not hide);
* ``write``: time spent waiting for PNG encoders and writing the tables;
* ``encode``: PNG encoding time summed over encoder threads (overlapped with rendering);
* ``total``: the whole call, compile included (``seconds_without_compile`` leaves it out).

``seconds_for_60s_estimated`` scales a shorter run to 60 s (compile once, the rest in
proportion); ``within_budget`` compares it with the 180 s budget.

The last line printed is one JSON object, e.g.
``{"seconds_total": 150.2, "pairs": 1200, "pairs_per_s": 8.0, ...}``.

The frames go through the default camera model (exposure x gain, shot and read noise, motion
blur; :mod:`uavcal_jax.sim.sensor`); ``--ideal-camera`` times the noise-free, sharp render
alone, the cost the camera model adds being the difference.

Usage::

    python experiments/bench_simulator.py                  # the issue's 60 s benchmark
    python experiments/bench_simulator.py --duration 5     # a quick run
    python experiments/bench_simulator.py --ideal-camera   # without the camera model
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

import jax
from _docs import (  # the script's folder is first on sys.path
    add_write_docs,
    figures_table,
    write_docs,
)

from uavcal_jax.argtypes import parse_resolution, print_json
from uavcal_jax.sim.config import COLORS, SimConfig
from uavcal_jax.sim.simulate import simulate_report

#: The issue's budget for 60 s of EuRoC-like data, seconds.
BUDGET_S = 180.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=60.0, help="flight seconds [60]")
    p.add_argument("--resolution", type=parse_resolution, default=SimConfig.resolution,
                   metavar="WxH")
    p.add_argument("--color", choices=COLORS, default=SimConfig.color)
    p.add_argument("--batch", type=int, default=SimConfig.batch_size, help="frames per call")
    p.add_argument("--workers", type=int, default=SimConfig.png_workers,
                   help="PNG encoder threads")
    p.add_argument("--seed", type=int, default=SimConfig.seed)
    p.add_argument("--ideal-camera", action="store_true",
                   help="noise-free, sharp frames (no exposure, noise or blur)")
    p.add_argument("--blur-samples", type=int, default=SimConfig.blur_samples,
                   help="sub-exposures averaged for motion blur")
    p.add_argument("--keep", type=Path, metavar="DIR", help="keep the output in DIR")
    p.add_argument("--no-progress", action="store_true")
    add_write_docs(p)
    args = p.parse_args(argv)

    config = SimConfig(duration=args.duration, resolution=args.resolution, color=args.color,
                       seed=args.seed, batch_size=args.batch, png_workers=args.workers,
                       ideal_camera=args.ideal_camera, blur_samples=args.blur_samples)
    tmp = None
    if args.keep is not None:
        out = args.keep
    else:
        tmp = tempfile.mkdtemp(prefix="uavcal-bench-sim-")
        out = Path(tmp) / "sim"
    try:
        report = simulate_report(config, out, progress=not args.no_progress)
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)

    t = report.timings
    counts = report.resolved["counts"]
    pairs = int(counts.get("frames", 0))
    total = t["total"]
    no_compile = total - t.get("compile", 0.0)
    result = {
        "seconds_total": round(total, 2),
        "seconds_without_compile": round(no_compile, 2),
        "pairs": pairs,
        "pairs_per_s": round(pairs / total, 2) if total > 0 else None,
        "pairs_per_s_without_compile": round(pairs / no_compile, 2) if no_compile > 0 else None,
        "flight_seconds": args.duration,
        "resolution": list(args.resolution),
        "color": args.color,
        "ideal_camera": args.ideal_camera,
        "blur_samples": None if args.ideal_camera else args.blur_samples,
        "imu_samples": counts["imu"],
        "target_rows": counts.get("target_rows", 0),
        "output_mb": round(size / 1e6, 1),
        "stages_s": {k: round(v, 2) for k, v in t.items()},
        "batch": args.batch,
        "workers": args.workers,
        "budget_s_for_60s": BUDGET_S,
        # compile once, the rest scales with the flight's length
        "seconds_for_60s_estimated": round(t.get("compile", 0.0) + no_compile * 60.0
                                           / args.duration, 1),
        "cpu_count": os.cpu_count(),
        "jax_backend": jax.default_backend(),
        "jax": jax.__version__,
        "python": platform.python_version(),
    }
    print(f"simulated {args.duration:g} s: {pairs} stereo pairs "
          f"{args.resolution[0]}x{args.resolution[1]} {args.color} + {counts['imu']} IMU "
          f"samples + depth + {result['target_rows']} target labels "
          f"in {total:.1f} s ({no_compile:.1f} s without compiling)", file=sys.stderr)
    for k, v in t.items():
        print(f"  {k:>16}: {v:8.2f} s", file=sys.stderr)
    result["within_budget"] = bool(result["seconds_for_60s_estimated"] <= BUDGET_S)
    write_docs(args, "bench_simulator", figures_table(result), argv=argv,
               anchor=f"the budget of {BUDGET_S:g} s for 60 s of data")
    print_json(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
