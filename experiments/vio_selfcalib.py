"""Self-calibration of a constant IMU offset by descending through the VIO window solve: the
command-line study around :func:`uavcal_jax.vio.selfcalib.recover_offset` (whose module
docstring describes the method).

``--windows`` synthetic windows share an injected constant offset (the defaults are of the size
of EuRoC's ground-truth biases, about 0.08 rad/s and 0.16 m/s^2 in norm); the estimate starts
at zero and descends on the mean converged window cost (``--method newton``: the
forward-difference Hessian, updated by BFGS; ``diag``: its diagonal; ``--lr``, ``--steps``).

Reported per channel: the injected offset, the estimate, ``|error|`` before (``= |o*|``, the
start is zero) and after, and the fraction removed ``1 - |err_after| / |err_before|``; per
sensor (3-vector norms) and overall in a scaled sense: each channel divided by its sensor's
EuRoC bias scale (0.08 rad/s, 0.16 m/s^2) before the 6-vector norm is taken. Also the
Cramer-Rao-like standard deviation of the estimate from the Hessian.

Prints a markdown table and, as the last line, one JSON object. The default run takes a few
minutes on a 2-core CPU, most of it compiling the solve and its backward rule once.

Usage::

    python experiments/vio_selfcalib.py
    python experiments/vio_selfcalib.py --windows 6 --steps 4 --seeds 2
    python experiments/vio_selfcalib.py --gyro=-0.05,0.02,0.03 --accel 0.1,0.1,-0.1
    python experiments/vio_selfcalib.py --large     # larger windows, more of them
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _docs import add_write_docs, write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import positive, positive_int, print_json
from uavcal_jax.vio.selfcalib import (
    DEFAULT_ACCEL,
    DEFAULT_GYRO,
    METHODS,
    DescentConfig,
    SelfCalibConfig,
    recover_offset,
)

CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")


def markdown_table(result: dict) -> str:
    """Per-channel table of one run (units: rad/s for g*, m/s^2 for a*)."""
    lines = ["| channel | injected | estimate | abs err before | abs err after | removed "
             "| sigma |", "|---|---|---|---|---|---|---|"]
    for i, name in enumerate(CHANNELS):
        lines.append(
            f"| {name} | {result['injected'][i]:+.4f} | {result['estimate'][i]:+.4f} "
            f"| {result['err_before'][i]:.4f} | {result['err_after'][i]:.2e} "
            f"| {100 * result['removed'][i]:.1f} % | {result['sigma'][i]:.1e} |")
    lines.append(
        f"\nremoved: gyro (norm) {100 * result['removed_gyro']:.1f} %, accel (norm) "
        f"{100 * result['removed_accel']:.1f} %, overall (channels / EuRoC bias scale "
        f"0.08 rad/s, 0.16 m/s^2) {100 * result['removed_scaled']:.1f} %; loss "
        f"{result['loss'][0]:.3f} -> {result['loss'][-1]:.3f}")
    return "\n".join(lines)


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z, got {text!r}")
    values = tuple(float(v) for v in parts)
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gyro", type=_triple, default=DEFAULT_GYRO,
                    help="injected gyro offset GX,GY,GZ rad/s (negative first value: "
                         "--gyro=-0.01,...) [default: 0.02,-0.03,0.015]")
    ap.add_argument("--accel", type=_triple, default=DEFAULT_ACCEL,
                    help="injected accel offset AX,AY,AZ m/s^2 [default: 0.1,-0.08,0.12]")
    ap.add_argument("--windows", type=positive_int, default=None,
                    help="windows sharing the offset [default: 4; --large: 8]")
    ap.add_argument("--seeds", type=positive_int, default=1,
                    help="independent runs (new windows each) [default: 1]")
    ap.add_argument("--steps", type=positive_int, default=5, help="descent steps [default: 5]")
    ap.add_argument("--method", choices=METHODS, default="newton")
    ap.add_argument("--lr", type=positive, default=1.0)
    ap.add_argument("--frames", type=positive_int, default=10)
    ap.add_argument("--landmarks", type=positive_int, default=None,
                    help="landmarks per window [default: 120; --large: 300]")
    ap.add_argument("--keyframe-dt", type=positive, default=0.15)
    ap.add_argument("--large", action="store_true",
                    help="a larger problem than the few-minute default: 8 windows of 300 landmarks")
    add_write_docs(ap)
    args = ap.parse_args(argv)

    windows = args.windows or (8 if args.large else 4)
    landmarks = args.landmarks or (300 if args.large else 120)
    offset = np.array(args.gyro + args.accel)
    t = time.perf_counter()
    runs, tables = [], []
    for seed in range(args.seeds):
        cfg = SelfCalibConfig(windows=windows, seed=seed, n_frames=args.frames,
                              n_landmarks=landmarks, keyframe_dt=args.keyframe_dt,
                              descent=DescentConfig(steps=args.steps, method=args.method,
                                                    lr=args.lr))
        res = recover_offset(offset, cfg, log=lambda s: print(s, file=sys.stderr))
        tables.append(f"Seed {seed}: {windows} windows x {args.frames} keyframes x {landmarks} "
                      f"landmarks, {args.method}, {args.steps} steps, {res['wall_s']:.0f} s\n\n"
                      + markdown_table(res))
        print(f"\n### {tables[-1]}")
        runs.append(res)
    wall_s = time.perf_counter() - t

    keys = ("estimate", "err_after", "removed", "sigma", "loss")
    out = {
        "injected": offset, "windows": windows, "frames": args.frames, "landmarks": landmarks,
        "keyframe_dt": args.keyframe_dt, "steps": args.steps, "method": args.method,
        "seeds": args.seeds,
        "runs": [{k: r[k] for k in keys + ("removed_gyro", "removed_accel", "removed_scaled",
                                             "wall_s")} for r in runs],
        "removed_min_channel": float(np.min([r["removed"] for r in runs])),
        "removed_scaled_mean": float(np.mean([r["removed_scaled"] for r in runs])),
        "loss_decreased": bool(all(r["loss"][-1] < r["loss"][0] for r in runs)),
        "wall_s": round(wall_s, 1),
    }
    write_docs(args, "vio_selfcalib", "\n\n".join(tables),
               anchor="the injected offset (abs err before)", argv=argv)
    print()
    print_json(out)
    return out


if __name__ == "__main__":
    main()
