"""Benchmark the whole stereo VIO: milliseconds per 752x480 stereo frame after warm-up.

Runs :class:`uavcal_jax.vio.estimator.StereoVio` (default :class:`VioConfig`) over the
stereo frames of a sequence -- by default the real ``../shared/data/euroc_v101_micro`` (95
frames of V1_01, a hover), optionally any EuRoC folder (``--sequence``, e.g. a simulated
flight from ``uavcal simulate``). Images are decoded before timing (decoding is not the VIO's
work). The sequence is played ``--passes`` times with a fresh estimator each pass; the first
pass compiles every jitted function and is reported apart (``compile_pass_s``), the others
are timed per frame, stages run one after the other, from the estimator's own stage clocks
(``FrameEstimate.timings``):
``frontend`` (IMU interval, preintegration, tracking), ``solve`` (insert, structured solve,
pruning), ``marginalize`` (the slide: drop or marginalisation) and ``total``; mean, median
and 95th percentile of each. Each timed pass is played again pipelined
(:func:`uavcal_jax.vio.run.estimate_stream`: the front end of the next frame in a worker
thread while the back end solves, as ``run_vio`` and ``uavcal vio`` do) and its wall-clock
time per frame reported as ``pipelined_wall_ms``. ``cpu_ms`` is the process's CPU time per
frame in the sequential passes (``time.process_time``, every thread): on a shared,
oversubscribed CPU the wall-clock figures include the time other processes held the cores,
the CPU time does not. The 1-minute load average before and after is recorded. Every pass
runs under :func:`uavcal_jax.vio.run.one_blas_thread`, as ``run_vio`` does.

The last line printed is one JSON object.

Usage::

    python experiments/bench_vio.py
    python experiments/bench_vio.py --sequence /tmp/sim/V1_02 --passes 2 --max-frames 200
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import warnings
from pathlib import Path

from _bench import stats  # the script's folder is first on sys.path
from _docs import add_write_docs, write_docs

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.results_doc import markdown_table
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.run import estimate_stream, one_blas_thread, stereo_pairs
from uavcal_jax.vio.stage_timer import TIMING_KEYS

DEFAULT_SEQUENCE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / \
    "euroc_v101_micro"
STAGES = TIMING_KEYS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    ap.add_argument("--passes", type=positive_int, default=3,
                    help="plays of the sequence; the first compiles [default: 3]")
    ap.add_argument("--max-frames", type=positive_int, default=None)
    ap.add_argument("--no-pipelined", action="store_true",
                    help="skip the pipelined passes (front end in a worker thread)")
    add_write_docs(ap)
    args = ap.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = read_euroc(args.sequence)
    pairs = stereo_pairs(seq)[:args.max_frames]
    cam0, cam1 = seq.camera("cam0"), seq.camera("cam1")
    images = [(t, cam0.load(i), cam1.load(j) if j is not None else None) for t, i, j in pairs]
    config = VioConfig()
    load_before = os.getloadavg()[0]
    per_stage = {k: [] for k in STAGES}
    wall_pipelined: list[float] = []
    cpu_ms: list[float] = []
    compile_s = None
    keyframes = resets = 0
    for p in range(args.passes):
        vio = StereoVio(cam0.calibration, cam1.calibration, seq.imu_calibration, seq.imu, config)
        t0 = time.perf_counter()
        frames, cpu = [], []
        with one_blas_thread():
            for t, left, right in images:
                c0 = time.process_time()
                frames.append(vio.process(t, left, right))
                cpu.append(1e3 * (time.process_time() - c0))
        if p == 0:
            compile_s = time.perf_counter() - t0
            continue
        keyframes += sum(f.keyframe for f in frames)
        resets += vio.resets
        cpu_ms += cpu[1:]
        for f in frames[1:]:  # frame 0 initialises
            for k in STAGES:
                per_stage[k].append(f.timings.get(k, 0.0))
        if not args.no_pipelined:
            vio = StereoVio(cam0.calibration, cam1.calibration, seq.imu_calibration, seq.imu,
                            config)
            loads = [(lambda im=im: im) for im in images]
            wall_pipelined += [f.timings["wall"] for f in estimate_stream(vio, loads)][1:]
    timed = len(per_stage["total"])
    out = {
        "sequence": str(args.sequence), "frames": len(images), "frames_timed": timed,
        "passes": args.passes, "compile_pass_s": compile_s,
        "keyframes_per_pass": keyframes / max(args.passes - 1, 1),
        "resets": resets,
        **{f"{k}_ms": stats(v) for k, v in per_stage.items() if v},
        "cpu_ms": stats(cpu_ms) if cpu_ms else None,
        "pipelined_wall_ms": stats(wall_pipelined) if wall_pipelined else None,
        "load_avg_1min": [load_before, os.getloadavg()[0]],
        "cpu_count": os.cpu_count(), "machine": platform.machine(),
        "config": {"keyframes": config.keyframes, "landmarks": config.landmarks,
                   "observations": config.observations,
                   "max_iterations": config.solver.max_iterations,
                   "max_features": config.frontend.max_features},
    }
    if timed:
        print(f"{timed} frames: mean {out['total_ms']['mean']:.1f} ms, "
              f"p95 {out['total_ms']['p95']:.1f} ms per stereo frame "
              f"(front end {out['frontend_ms']['mean']:.1f}, solve {out['solve_ms']['mean']:.1f}, "
              f"marginalisation {out['marginalize_ms']['mean']:.1f}; CPU "
              f"{out['cpu_ms']['mean']:.1f})")
    if wall_pipelined:
        print(f"pipelined (front end one frame ahead in a thread): mean "
              f"{out['pipelined_wall_ms']['mean']:.1f} ms, p95 "
              f"{out['pipelined_wall_ms']['p95']:.1f} ms wall-clock per frame")
    write_docs(args, "bench_vio", markdown_table(
        ("ms per stereo frame", "mean", "median", "p95"),
        [(k.removesuffix("_ms"), *(f"{v[s]:.1f}" for s in ("mean", "median", "p95")))
         for k, v in out.items() if k.endswith("_ms") and isinstance(v, dict)]),
        anchor="RPEOD on an NVIDIA Jetson Xavier NX: 46.5 ms per frame (mean of its Table 2)")
    print_json(out)


if __name__ == "__main__":
    main()
