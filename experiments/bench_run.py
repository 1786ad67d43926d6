"""Benchmark ``uavcal run``'s whole pipeline: milliseconds per 752x480 stereo frame in steady
state, split by stage, beside the VIO alone in the same run.

The recording is a simulated procedural flight past a moving car at EuRoC's 752x480 (rendered
once into ``--cache``), or any recording with ``--sequence``. Each pass runs
:func:`uavcal_jax.pipeline.run.run_pipeline` with the shipped detector on every left frame,
concurrently with the VIO as the run does, then locates, filters and follows the target. The
IMU offset is given (zeros): estimating it is a one-off before the flight, not per-frame
work. Passes alternate with the VIO alone (:func:`uavcal_jax.vio.run.run_vio`, the same
settings), so both see the same machine load. The first pass of each compiles and is reported
apart (``compile_pass_s``); the others are timed.

Figures, per frame (medians over the timed passes):

* ``pipeline_wall_ms``: measured wall-clock throughput, (VIO and detector running together +
  tracking and set-points) / frames. It includes image decoding (PNG) for both stages and the
  VIO's initialisation frames; this is the number the 50 ms (20 Hz) budget is held against.
* ``stages_ms``: the run's own per-stage steady-state means (``metrics.json``'s
  ``ms_per_frame``: ``vio_wall`` with the detector beside it, ``detect``, ``locate``,
  ``filter``, ``follow``, and their ``pipeline`` combination).
* ``vio_alone_wall_ms``: the VIO alone, wall-clock / frames, and its per-frame mean.

The 1-minute load average before and after is recorded: on a shared 2-core machine another
process's work shows up in every wall-clock figure.

The last line printed is one JSON object.

Usage::

    python experiments/bench_run.py                    # ~4 min on 2 cores, first time ~5
    python experiments/bench_run.py --sequence sim/ --passes 2
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from _bench import median  # the script's folder is first on sys.path
from _docs import add_write_docs, figures_table, write_docs

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.data.read import read_sequence
from uavcal_jax.pipeline.detectors import load_network_detector
from uavcal_jax.pipeline.run import run_pipeline
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.sim.cache import cached_simulation
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.vio.run import run_vio

ROOT = Path(__file__).resolve().parents[1]
#: The benchmark's flight: procedural, EuRoC's 752x480 and 20 Hz, one moving car in view.
BENCH_FLIGHT = SimConfig(duration=10.0, seed=7, follow_targets=1)
STAGES = ("vio_wall", "detect", "locate", "filter", "follow", "pipeline")


def _pipeline_pass(recording: Path, config: RunConfig, detector, out: Path) -> dict:
    result = run_pipeline(recording, out, config, offsets=np.zeros(6), offsets_from="zeros",
                          detector=detector, progress=False)
    m = result.metrics
    frames = m["vio"]["frames"]
    seconds = m["seconds"]["vio_and_detect"] + m["seconds"]["track_and_follow"]
    return {"wall_ms": 1e3 * seconds / frames, "frames": frames,
            "stages": {k: (m["ms_per_frame"][k] or {}).get("mean") for k in STAGES},
            "target_error_m": m["target_error_m"], "ate_m": m["ate_m"]}


def _vio_pass(recording: Path, config: RunConfig) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence, _ = read_sequence(recording)
    t0 = time.perf_counter()
    vio = run_vio(sequence, config.vio, show_progress=False)
    wall = time.perf_counter() - t0
    per_frame = vio.timings()["wall"][config.warmup_frames:]
    return {"wall_ms": 1e3 * wall / len(vio.frames), "frame_mean_ms": float(np.mean(per_frame))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=None,
                    help="a recording with a stereo pair [default: the simulated flight]")
    ap.add_argument("--passes", type=positive_int, default=3,
                    help="passes of each; the first compiles [default: 3]")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "bench_cache")
    add_write_docs(ap)
    args = ap.parse_args()
    recording = args.sequence or cached_simulation(BENCH_FLIGHT, args.cache, "bench_run")
    config = RunConfig()
    detector = load_network_detector(None, config.detect.detector_threshold())
    load_before = os.getloadavg()[0]
    pipeline, alone, compile_s = [], [], {}
    with tempfile.TemporaryDirectory(prefix="bench-run-") as tmp:
        for p in range(args.passes):
            t0 = time.perf_counter()
            run = _pipeline_pass(recording, config, detector, Path(tmp) / f"run{p}")
            t1 = time.perf_counter()
            vio = _vio_pass(recording, config)
            if p == 0:
                compile_s = {"pipeline": t1 - t0, "vio_alone": time.perf_counter() - t1}
                continue
            pipeline.append(run)
            alone.append(vio)
            print(f"pass {p}: pipeline {run['wall_ms']:.1f} ms/frame, VIO alone "
                  f"{vio['wall_ms']:.1f} ms/frame", flush=True)
    out = {
        "sequence": str(recording), "frames": pipeline[0]["frames"] if pipeline else None,
        "passes": args.passes, "compile_pass_s": compile_s,
        "pipeline_wall_ms": median([r["wall_ms"] for r in pipeline]) if pipeline else None,
        "stages_ms": {k: median([r["stages"][k] for r in pipeline
                                 if r["stages"][k] is not None] or [np.nan])
                      for k in STAGES} if pipeline else None,
        "vio_alone_wall_ms": median([r["wall_ms"] for r in alone]) if alone else None,
        "vio_alone_frame_mean_ms": median([r["frame_mean_ms"] for r in alone]) if alone else None,
        "budget_ms": 50.0,
        "target_error_m": pipeline[-1]["target_error_m"] if pipeline else None,
        "ate_m": pipeline[-1]["ate_m"] if pipeline else None,
        "detect_every": config.detect.every,
        "load_avg_1min": [load_before, os.getloadavg()[0]],
        "cpu_count": os.cpu_count(), "machine": platform.machine(),
    }
    if pipeline:
        out["pipeline_over_vio_alone"] = out["pipeline_wall_ms"] / out["vio_alone_wall_ms"]
        print(f"whole pipeline {out['pipeline_wall_ms']:.1f} ms per stereo frame (budget 50), "
              f"VIO alone {out['vio_alone_wall_ms']:.1f} ms")
    write_docs(args, "bench_run", figures_table(
        {**out, **{f"stage {k} (ms)": v for k, v in (out["stages_ms"] or {}).items()}}),
        anchor="`uavcal vio` alone on the same flight, same run; EuRoC's 50 ms frame budget")
    print_json(out)


if __name__ == "__main__":
    main()
