"""Benchmark the VIO front end: milliseconds per 752x480 stereo frame on real EuRoC frames.

Runs :class:`uavcal_jax.vio.frontend.FeatureTracker` (default :class:`FrontendConfig`: 150
corners, LK 21x21 with 3 pyramid levels, forward-backward checks, USAC outlier rejection,
left-to-right tracking) over the stereo frames of ``../shared/data/euroc_v101_micro`` (95
frames of V1_01). The images are decoded before timing (disk and PNG decoding are not the
front end's work). The sequence is played ``--passes`` times, the tracker reset between passes
so each pass starts with a detection as a real run does; the first ``--warmup`` frames are not
timed (OpenCV allocates its buffers and the CPU caches warm up there).

Reported, wall-clock from the tracker's own stage clocks (``FeatureTracker.last_timings``):
median and 95th percentile of the total per stereo frame and of each stage -- ``preprocess``
(equalisation), ``temporal`` (left frame-to-frame LK and its backward check), ``outlier``
(RANSAC), ``detect`` (the min-distance mask, Shi-Tomasi corners when needed,
undistortion) and ``stereo`` (left-to-right LK, its backward check and the epipolar gate);
also the mean total, the tracked and stereo corners per frame and how many frames detected.
``cpu_median_ms`` / ``cpu_p95_ms`` are the process's CPU time per frame
(``time.process_time``): on a shared, oversubscribed CPU the wall-clock figures include the
time other processes held the core, the CPU time does not (with one OpenCV thread it is what
the frame costs on a core of its own). The 1-minute load average before and after is
recorded beside them.

Threads: ``cv2.setNumThreads(--threads)``, 1 by default. The front end is one of several
stages sharing this 2-core CPU with the back end's XLA threads; its OpenCV calls work on 150
points and one image, too little to gain from a thread pool (measured here: 2 threads were
no faster), and 1 thread keeps the figures stable on a shared machine.

The CPU is often shared; run it on a quiet machine for stable numbers. The last line printed
is one JSON object.

Usage::

    python experiments/bench_vio_frontend.py
    python experiments/bench_vio_frontend.py --threads 2 --passes 3
    python experiments/bench_vio_frontend.py --equalize clahe
    python experiments/bench_vio_frontend.py --redetect-below 150   # VINS: top up every frame

The micro slice starts with the MAV nearly still (most tracks live through all 95 frames),
so with RPEOD's threshold of 120 it detects in the first frame of each pass only;
``--redetect-below 150`` prices the detection into every frame that lost a corner.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
from _bench import stats  # the script's folder is first on sys.path
from _docs import add_write_docs, write_docs

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.results_doc import markdown_table
from uavcal_jax.vio.config import EQUALIZERS, FrontendConfig
from uavcal_jax.vio.frontend import FeatureTracker

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "euroc_v101_micro"
STAGES = ("preprocess", "temporal", "outlier", "detect", "stereo", "total")


def load_frames(root: Path):
    """The sequence and its decoded stereo frames ``[(t, left, right), ...]``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = read_euroc(root)
    c0, c1 = seq.camera("cam0"), seq.camera("cam1")
    n = min(len(c0), len(c1))
    return seq, [(float(c0.t[i]), c0.load(i), c1.load(i)) for i in range(n)]


def run(seq, frames, config: FrontendConfig, passes: int, warmup: int) -> dict:
    """Track ``frames`` ``passes`` times; the timing statistics of the frames after ``warmup``."""
    tracker = FeatureTracker.from_sequence(seq, config)
    rows, cpu, tracked, stereo, detected = [], [], [], [], 0
    k = 0
    for _ in range(passes):
        tracker.reset()
        for t, left, right in frames:
            c0 = time.process_time()
            f = tracker.track(t, left, right)
            c1 = time.process_time()
            if k >= warmup:
                rows.append([tracker.last_timings[s] for s in STAGES])
                cpu.append(1e3 * (c1 - c0))
                tracked.append(f.n_tracked)
                stereo.append(f.n_stereo)
                detected += f.n_new > 0
            k += 1
    ms = np.asarray(rows)
    cpu_stats = stats(cpu)
    out = {"frames_timed": len(rows), "frames_detected": int(detected),
           "mean_ms": float(ms[:, -1].mean()),
           "cpu_median_ms": cpu_stats["median"], "cpu_p95_ms": cpu_stats["p95"],
           "tracked_per_frame": float(np.mean(tracked)),
           "stereo_per_frame": float(np.mean(stereo))}
    for j, stage in enumerate(STAGES):
        name = "" if stage == "total" else f"{stage}_"
        stage_stats = stats(ms[:, j])
        out[f"{name}median_ms"] = stage_stats["median"]
        out[f"{name}p95_ms"] = stage_stats["p95"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="EuRoC folder (holds mav0)")
    ap.add_argument("--threads", type=positive_int, default=1, help="cv2.setNumThreads")
    ap.add_argument("--passes", type=positive_int, default=2, help="plays of the sequence")
    ap.add_argument("--warmup", type=int, default=10, help="untimed frames at the start")
    ap.add_argument("--equalize", choices=EQUALIZERS, default=FrontendConfig().equalize)
    ap.add_argument("--redetect-below", type=int, default=FrontendConfig().redetect_below,
                    help="detect new corners below this many tracks (150: every frame that "
                         "lost one, as VINS-Fusion)")
    add_write_docs(ap)
    args = ap.parse_args(argv)
    if not args.data.exists():
        print(f"no EuRoC data at {args.data}", file=sys.stderr)
        return 1
    cv2.setNumThreads(args.threads)
    seq, frames = load_frames(args.data)
    config = dataclasses.replace(FrontendConfig(), equalize=args.equalize,
                                 redetect_below=args.redetect_below)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    result = run(seq, frames, config, args.passes, args.warmup)
    wall = time.perf_counter() - t0
    result["load_avg_1min"] = [load_before, os.getloadavg()[0]]
    print(f"{result['frames_timed']} stereo frames {frames[0][1].shape[1]}x"
          f"{frames[0][1].shape[0]}, {args.threads} OpenCV thread(s), equalize={args.equalize}")
    for stage in STAGES:
        name = "" if stage == "total" else f"{stage}_"
        print(f"  {stage:>10}: median {result[f'{name}median_ms']:6.2f} ms   "
              f"p95 {result[f'{name}p95_ms']:6.2f} ms")
    print(f"  CPU time of the process: median {result['cpu_median_ms']:.2f} ms, p95 "
          f"{result['cpu_p95_ms']:.2f} ms per frame (1-min load average "
          f"{result['load_avg_1min'][0]:.1f} -> {result['load_avg_1min'][1]:.1f} on "
          f"{os.cpu_count()} cores)")
    print(f"  corners tracked {result['tracked_per_frame']:.1f}, stereo "
          f"{result['stereo_per_frame']:.1f} per frame; detection in "
          f"{result['frames_detected']} frames; {wall:.1f} s in all")
    prefix = {stage: "" if stage == "total" else f"{stage}_" for stage in STAGES}
    write_docs(args, "bench_vio_frontend", markdown_table(
        ("ms per stereo frame", "median", "p95"),
        [(stage, *(f"{result[f'{prefix[stage]}{s}_ms']:.2f}" for s in ("median", "p95")))
         for stage in STAGES]), argv=argv,
        anchor="the whole VIO's time per frame (bench_vio)")
    print_json({**result, "threads": args.threads, "equalize": args.equalize,
                "width": int(frames[0][1].shape[1]), "height": int(frames[0][1].shape[0]),
                "opencv": cv2.__version__, "cpu_count": os.cpu_count(),
                "machine": platform.machine(), "config": dataclasses.asdict(config)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
