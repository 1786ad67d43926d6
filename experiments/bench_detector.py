"""Speed and size of the detectors on this machine's CPU (RPEOD Table 3's FPS column).

For each model (YZNet-YOLO-tiny first, then YZNet-YOLO and the YOLOv5n-like baseline) the
whole inference path -- network, box decoding and NMS -- is one jitted function
(:func:`uavcal_jax.detect.predict.make_predict_fn`), batch 1, a 640x480 (H=480, W=640)
float32 image. It is compiled first (``compile_s``, timed apart), warmed up, then timed over
``--runs`` calls (``ms_median``, ``ms_min``; ``fps = 1000 / ms_median``).

Weights: random initialisation by default (YOLOv5's head bias init makes almost nothing pass
``conf_thresh = 0.25``, so NMS has little to do); ``--worst-case`` also times
``conf_thresh = 0.001`` with ``max_det = 300``, where the pre-NMS top-k is full (1,000
candidates) and NMS keeps up to 300 boxes -- an upper bound on the cost of a trained model.
``--variables PATH`` (a ``.msgpack`` of ``{"params", "batch_stats"}`` written by
``flax.serialization.to_bytes``) times trained weights instead.

Also reported: the classification YZNet's parameters and multiply-adds at 224x224 (paper:
about 1.74 M and 5.9e7) and each detector's parameters and GFLOPs (2 x multiply-adds) at the
input size. ``--dw-sweep`` times the depthwise-convolution implementations on the YZNet layer
shapes first (the reason ``dw_impl="shift"`` is the default). ``--frame`` also times the
shipped detector as ``uavcal run`` calls it (:class:`uavcal_jax.pipeline.detectors.
NetworkDetector`: letterbox, network, NMS, boxes back into the frame) on one 640x480 uint8
frame, whole and sliced (``detect.tile``: windows of the network input plus the whole frame,
one batch, merged): ``frame`` in the JSON.

The machine's cores may be shared; the median of many runs is robust to short bursts, and
``ms_min`` shows the uncontended speed; ``cpu_ms_median`` is the process CPU time per call
(both cores together), a load-independent measure of the work done. The last line printed
is one JSON object.

What was measured before choosing the implementation (this 2-core AMD EPYC, XLA:CPU, jax
0.10; ms per call, medians, the machine shared with other jobs):

* depthwise convolutions: Flax's grouped ``conv_general_dilated`` vs a sum of ``k*k`` shifted,
  per-channel-scaled slices (``dw_impl="shift"``): 22.6 vs 2.5 ms on 120x160x72 (3x3, /2),
  32.0 vs 0.5 on 60x80x88, 12.9 vs 0.7 on 30x40x240 (5x5) -- the whole tiny network 160 vs
  67 ms at the time, and a training step 11.7 vs 3.0 s (batch 8). Identical to 1e-5 (tests).
* 1x1 convolutions as ``jnp.dot`` (XLA hands it to its YNNPACK GEMM) instead of a 1x1
  ``conv_general_dilated``: 0.54 vs 1.24 ms on 120x160x72 -> 24; the network 27 -> 17 ms.
* the 3-channel stride-2 stems as a space-to-depth convolution: 2.3 vs 3.1 ms; SPPF's 5x5
  max pools as separable shifted maxima instead of ``reduce_window``; boxes decoded only for
  the 1,000 best candidates: post-processing 1.1 -> 0.4 ms.
* no gain beyond the noise: folding batch norm into the convolutions (XLA already fuses the
  BN affine into the elementwise pass after each product), and the XLA flags
  ``--xla_cpu_use_xnnpack=false``, ``--xla_cpu_enable_fast_math=true``,
  ``--xla_cpu_multi_thread_eigen=false``, ``--xla_cpu_use_onednn=true`` (slower),
  ``--xla_cpu_experimental_ynn_fusion_type=-reduce`` and ``=dot``; ``XLA_FLAGS`` is recorded
  in the output so such runs can be compared. Everything runs in float32.

Usage::

    python experiments/bench_detector.py                  # all three models, 30 runs each
    python experiments/bench_detector.py --models yznet-yolo-tiny --runs 50 --worst-case
    python experiments/bench_detector.py --dw-sweep
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys

import jax
import jax.numpy as jnp
from _bench import time_calls, time_compile, time_once  # the script's folder is on sys.path
from _docs import add_write_docs, write_docs

from uavcal_jax.data.results_doc import markdown_table
from uavcal_jax.detect.config import (
    DW_IMPLS,
    EVAL_PREDICT,
    MODELS,
    SERVE_PREDICT,
    DetectorConfig,
)
from uavcal_jax.detect.counting import classifier_counts, detector_counts
from uavcal_jax.detect.layers import depthwise_grouped, depthwise_shift
from uavcal_jax.detect.model import init_detector
from uavcal_jax.detect.predict import make_predict_fn

#: Untimed calls after the compile.
WARMUP = 3


def bench_model(model: str, args, image) -> dict:
    cfg = DetectorConfig(model=model, num_classes=args.num_classes, img_size=(args.h, args.w),
                         dw_impl=args.dw_impl)
    if args.variables and model == args.models[0]:
        from flax import serialization

        template = init_detector(jax.random.key(0), cfg)
        with open(args.variables, "rb") as f:
            variables = serialization.from_bytes(template, f.read())
    else:
        variables = init_detector(jax.random.key(args.seed), cfg)
    res = {"model": model, **detector_counts(cfg)}
    settings = [("", SERVE_PREDICT.replace(conf_thresh=args.conf_thresh, max_det=args.max_det))]
    if args.worst_case:  # the evaluation's low threshold and full output, one label per box
        settings.append(("worst_", SERVE_PREDICT.replace(conf_thresh=EVAL_PREDICT.conf_thresh,
                                                         max_det=EVAL_PREDICT.max_det)))
    for prefix, predict_cfg in settings:
        conf, max_det = predict_cfg.conf_thresh, predict_cfg.max_det
        fn = make_predict_fn(cfg, predict_cfg)
        compiled, compile_s = time_compile(fn, variables, image)
        timed = time_calls(functools.partial(compiled, variables, image), repeats=args.runs,
                           warmup=WARMUP)
        det = timed.result
        res.update({
            f"{prefix}conf_thresh": conf,
            f"{prefix}max_det": max_det,
            f"{prefix}compile_s": round(compile_s, 3),
            f"{prefix}ms_median": round(1e3 * timed.median_s, 3),
            f"{prefix}ms_min": round(1e3 * timed.min_s, 3),
            f"{prefix}ms_p90": round(1e3 * timed.percentile_s(90), 3),
            f"{prefix}cpu_ms_median": round(1e3 * timed.cpu_median_s, 3),
            f"{prefix}fps": round(1.0 / timed.median_s, 2),
            f"{prefix}detections": int(det.valid.sum()),
        })
    return res


def bench_frame(runs: int) -> dict:
    """The shipped detector's whole path on a 640x480 frame (a rendered-like random frame),
    untiled and tiled (:class:`~uavcal_jax.detect.tile.TileConfig` defaults): ms per frame
    (median, min), frames/s, the first call's seconds (the compile) and the windows."""
    import numpy as np

    from uavcal_jax.detect.tile import TileConfig, tile_windows
    from uavcal_jax.pipeline.detectors import load_network_detector

    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    out = {"frame_hw": [480, 640]}
    for name, tile in (("whole", None), ("tiled", TileConfig())):
        detector = load_network_detector(None, SERVE_PREDICT.conf_thresh, tile)
        _, first_s = time_once(lambda d=detector: d([frame], [0]))
        timed = time_calls(lambda d=detector: d([frame], [0]), repeats=runs, warmup=WARMUP)
        out[name] = {"ms_median": round(1e3 * timed.median_s, 2),
                     "ms_min": round(1e3 * timed.min_s, 2),
                     "cpu_ms_median": round(1e3 * timed.cpu_median_s, 2),
                     "fps": round(1.0 / timed.median_s, 2), "first_call_s": round(first_s, 2)}
        if tile is not None:
            out[name]["windows"] = len(tile_windows((480, 640), detector.img_size,
                                                    tile.overlap))
            out[name]["batch"] = tile.batch_size
    out["img_size"] = list(detector.img_size)
    return out


def dw_sweep(runs: int) -> list[dict]:
    """Time depthwise implementations on the YZNet layer shapes at 640x480."""
    shapes = [(240, 320, 16, 3, 2), (120, 160, 72, 3, 2), (60, 80, 88, 3, 1),
              (60, 80, 96, 5, 2), (30, 40, 240, 5, 1), (30, 40, 480, 5, 2), (15, 20, 600, 5, 1)]
    rows = []
    for h, w, c, k, s in shapes:
        x = jax.random.normal(jax.random.key(0), (1, h, w, c))
        kern = jax.random.normal(jax.random.key(1), (k, k, 1, c))
        row = {"shape": [h, w, c], "k": k, "stride": s}
        ref = None
        for name, f in (("shift", depthwise_shift), ("grouped", depthwise_grouped)):
            jf = jax.jit(f, static_argnums=2)
            out = jf(x, kern, s)
            ref = out if ref is None else ref
            timed = time_calls(functools.partial(jf, x, kern, s), repeats=runs, warmup=WARMUP)
            row[f"{name}_ms"] = round(1e3 * timed.median_s, 3)
            row[f"{name}_maxdiff"] = float(jnp.max(jnp.abs(out - ref)))
        print(json.dumps(row), file=sys.stderr, flush=True)
        rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    p.add_argument("--runs", type=int, default=30, help="timed calls per model [30]")
    p.add_argument("--h", type=int, default=DetectorConfig.img_size[0])
    p.add_argument("--w", type=int, default=DetectorConfig.img_size[1])
    p.add_argument("--num-classes", type=int, default=5, help="[5: the aerial car classes]")
    p.add_argument("--conf-thresh", type=float, default=SERVE_PREDICT.conf_thresh)
    p.add_argument("--max-det", type=int, default=SERVE_PREDICT.max_det)
    p.add_argument("--dw-impl", default=DetectorConfig.dw_impl, choices=DW_IMPLS)
    p.add_argument("--worst-case", action="store_true",
                   help=f"also time conf {EVAL_PREDICT.conf_thresh:g}, {EVAL_PREDICT.max_det} "
                        "dets")
    p.add_argument("--variables", help="trained variables (.msgpack) for the first model")
    p.add_argument("--dw-sweep", action="store_true")
    p.add_argument("--frame", action="store_true",
                   help="also time the shipped detector on a 640x480 frame, whole and tiled")
    p.add_argument("--seed", type=int, default=0)
    add_write_docs(p)
    args = p.parse_args(argv)

    summary: dict = {
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "input_hw": [args.h, args.w],
        "runs": args.runs,
        "dw_impl": args.dw_impl,
    }
    if args.dw_sweep:
        summary["dw_sweep"] = dw_sweep(max(args.runs // 2, 5))
    if args.frame:
        summary["frame"] = bench_frame(args.runs)
        f = summary["frame"]
        print(f"shipped detector, 640x480 frame: whole {f['whole']['ms_median']:.1f} ms "
              f"({f['whole']['fps']:.1f} fps), tiled ({f['tiled']['windows']} windows + the "
              f"frame) {f['tiled']['ms_median']:.1f} ms ({f['tiled']['fps']:.1f} fps)",
              file=sys.stderr, flush=True)
    cls = classifier_counts(20, 224)
    summary["params_classifier"] = cls["params"]
    summary["macs_classifier"] = cls["macs"]
    summary["params_classifier_paper"] = 1_740_000
    summary["macs_classifier_paper"] = 59_000_000
    image = jax.random.uniform(jax.random.key(1), (1, args.h, args.w, 3), jnp.float32)
    results = {}
    for model in args.models:
        r = bench_model(model, args, image)
        results[model] = r
        worst = f"; worst case {r['worst_fps']:.1f} fps" if "worst_fps" in r else ""
        print(f"{model}: {r['params']:,} params, {r['gflops']:.2f} GFLOPs, compile "
              f"{r['compile_s']:.1f} s, {r['ms_median']:.2f} ms median ({r['ms_min']:.2f} min) "
              f"= {r['fps']:.1f} fps, CPU {r['cpu_ms_median']:.1f} ms{worst}",
              file=sys.stderr, flush=True)
    first = results[args.models[0]]
    summary.update({
        "model": args.models[0],
        "fps": first["fps"],
        "ms_per_frame": first["ms_median"],
        "ms_min": first["ms_min"],
        "compile_s": first["compile_s"],
        "params_detector": first["params"],
        "gflops_detector": round(first["gflops"], 4),
    })
    if "worst_fps" in first:
        summary["worst_fps"] = first["worst_fps"]
    for model, r in results.items():
        key = model.replace("-", "_")
        summary[key] = {k: v for k, v in r.items() if k != "model"}
    write_docs(args, "bench_detector", markdown_table(
        ("model", "params", "GFLOPs", "ms per frame (median)", "frames/s"),
        [(m, f"{r['params']:,}", f"{r['gflops']:.2f}", f"{r['ms_median']:.2f}", f"{r['fps']:.1f}")
         for m, r in results.items()]), argv=argv,
        anchor=f"{args.w}x{args.h}, batch 1, NMS included; the models against each other")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
