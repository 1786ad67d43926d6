"""The stereo VIO through a visual dropout, with and without a learned prior on its biases
(issue 43, item 3; Buchanan et al. 2022).

Each flight (simulated along a real trajectory, with its own physical-range IMU offset, as
``calib_blind.py`` makes them) goes blind for ``--dropout`` seconds from ``--dropout-start``
(every frame black, or blurred past use: ``--kind``;
:func:`uavcal_jax.data.frame_dropout.with_frame_dropout`). On that recording:

- ``plain``: the VIO as it is (its biases start at zero under the sensor's turn-on prior);
- ``removed``: the learned estimate (``--method``, default the ``transformer``, run on the
  same blinded recording without ground truth) removed from the IMU first, the prior as is;
- ``prior``: removed, and its sigma as the prior on the biases
  (:func:`uavcal_jax.pipeline.bias_prior.run_vio_with_prior`);
- ``oracle``: the true constant error (the simulator's offset plus the sensor's own mean
  bias) removed under the tightest prior: how much of the drift any bias prior can take away.

Scored against the simulator's ground truth: the drift (:func:`uavcal_jax.pipeline.
drift_metrics.drift_curve`: heading and offset fitted over the path flown before the dropout,
then left alone) at the end of the flight and its largest value after the dropout began.

Usage::

    python experiments/vio_dropout.py --cache /work/exp/blind_cache
    python experiments/vio_dropout.py --kind blur --flights MH_04_difficult,V1_03_difficult

Writes ``OUT/results.json`` and ``OUT/table.md``; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from _calib_common import ROOT  # the script's folder is first on sys.path
from _docs import add_write_docs, write_docs  # the script's folder is first on sys.path
from calib_blind import flight_names, simulated_flights

from uavcal_jax.data.frame_dropout import DROPOUT_KINDS, with_frame_dropout
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.pipeline.bias_prior import prior_from_estimate, run_vio_with_prior
from uavcal_jax.pipeline.drift_metrics import drift_curve, path_length
from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS
from uavcal_jax.pipeline.offset_estimators import configure_method
from uavcal_jax.pipeline.predict_offset import known_offset, predict_offset, score
from uavcal_jax.vio.run import run_vio

#: The VIO variants, in the table's order.
VARIANTS = ("plain", "removed", "prior", "oracle")


def _drift(result, ground_truth, dropout_t0_ns: int) -> dict:
    """Final and worst drift after the dropout began, heading and offset fitted over the path
    flown before it."""
    traj = result.trajectory()
    t = np.asarray(ground_truth.t_ns, np.int64)
    before = t < dropout_t0_ns
    align_m = float(path_length(ground_truth.position[before])[-1]) if before.sum() > 1 else 1.0
    curve = drift_curve(traj, ground_truth, align_m=max(align_m, 0.5))
    after = curve["t_ns"] >= dropout_t0_ns
    return {"final_m": float(curve["error_m"][-1]),
            "max_after_m": float(curve["error_m"][after].max()) if after.any() else None,
            "resets": result.resets, "path_m": float(curve["distance_m"][-1])}


def run_flight(folder: Path, args) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence, _ = read_sequence(folder)
    blind = with_frame_dropout(sequence, args.dropout_start, args.dropout, args.kind)
    t0 = int(sequence.camera("cam0").t_ns[0]) + int(round(args.dropout_start * 1e9))
    options = configure_method(args.method, checkpoint=args.checkpoint) \
        if args.method in ("transformer", "auto") else configure_method(args.method)
    tic = time.perf_counter()
    _, estimate = predict_offset(blind, args.method, options)
    est_s = time.perf_counter() - tic
    truth = known_offset(recorded_imu_offset(folder), None)
    scored = score(estimate, truth, sequence.ground_truth, all_channels=True)
    prior = prior_from_estimate(estimate)
    row = {"flight": folder.name, "estimate": estimate.offset.tolist(),
           "sigma": None if estimate.sigma is None else estimate.sigma.tolist(),
           "estimate_error": scored["error"], "estimate_s": round(est_s, 1),
           "prior": {"bias_gyro": prior.bias_gyro, "bias_accel": prior.bias_accel}}
    oracle = dataclasses.replace(estimate, offset=np.asarray(scored["true"]),
                                 median=np.asarray(scored["true"]), channels=SIX_CHANNELS,
                                 per_item=np.asarray(scored["true"])[None],
                                 item_t_s=np.zeros(1), sigma=np.full(6, 1e-9))
    runs = {"plain": lambda: run_vio(blind),
            "removed": lambda: run_vio(blind, imu_offset=estimate.offset),
            "prior": lambda: run_vio_with_prior(blind, estimate),
            "oracle": lambda: run_vio_with_prior(blind, oracle)}
    for name in VARIANTS:
        tic = time.perf_counter()
        row[name] = {**_drift(runs[name](), sequence.ground_truth, t0),
                     "seconds": round(time.perf_counter() - tic, 1)}
    if not args.quiet:
        print(f"{folder.name}: " + ", ".join(f"{v} {row[v]['final_m']:.3f} m"
                                             for v in VARIANTS), file=sys.stderr, flush=True)
    return row


def _table(rows: list[dict], args) -> str:
    lines = [f"{args.dropout:g} s of {args.kind} frames from {args.dropout_start:g} s into each "
             f"{args.duration:g} s flight; learned estimate: `{args.method}` on the blinded "
             "recording. Drift: position error after fitting heading and offset over the path "
             "before the dropout.", "",
             "| flight | path (m) | estimate's accel error (m/s^2, RMS) | plain: final / worst "
             "(m) | offset removed | with the prior | true offset, tightest prior | "
             "prior / plain (final) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        acc = np.sqrt(np.mean(np.square(r["estimate_error"][3:])))
        cells = [f"{r[v]['final_m']:.3f} / {r[v]['max_after_m']:.3f}" for v in VARIANTS]
        lines.append(f"| {r['flight']} | {r['plain']['path_m']:.1f} | {acc:.3f} | "
                     + " | ".join(cells)
                     + f" | {r['prior']['final_m'] / max(r['plain']['final_m'], 1e-9):.2f} |")
    final = {v: np.mean([r[v]["final_m"] for r in rows]) for v in VARIANTS}
    lines.append(f"| mean of {len(rows)} | | | {final['plain']:.3f} | {final['removed']:.3f} | "
                 f"{final['prior']:.3f} | {final['oracle']:.3f} | "
                 f"{final['prior'] / max(final['plain'], 1e-9):.2f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", type=flight_names,
                    default=[n for n in flight_names("all") if n[:2] in ("MH", "V1", "V2")],
                    help="trajectory names, comma-separated, or 'all' [default: the 11 EuRoC]")
    ap.add_argument("--start", type=float, default=10.0)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--dropout-start", type=float, default=8.0, help="seconds into the flight")
    ap.add_argument("--dropout", type=float, default=5.0, help="seconds of dropout")
    ap.add_argument("--kind", choices=DROPOUT_KINDS, default="black")
    ap.add_argument("--method", default="transformer",
                    help="the learned estimate's method [default: %(default)s]")
    ap.add_argument("--checkpoint", type=Path, default=None,
                    help="the transformer's run folder [default: the shipped weights]")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "calib_cache")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "out" / "vio_dropout")
    ap.add_argument("--quiet", action="store_true")
    add_write_docs(ap)
    args = ap.parse_args()
    args.imu_rotation = None
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [run_flight(folder, args) for folder in simulated_flights(args)]
    table = _table(rows, args)
    (args.out / "table.md").write_text(table)
    (args.out / "results.json").write_text(json.dumps({"rows": rows, "argv": sys.argv[1:]},
                                                      indent=1) + "\n")
    print(table)
    write_docs(args, "vio_dropout", table, anchor="the same VIO without the prior, same run")
    print(json.dumps({"flights": len(rows), "mean_final_m": {
        v: float(np.mean([r[v]["final_m"] for r in rows])) for v in VARIANTS}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
