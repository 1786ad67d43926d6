"""Drift over long flights with and without the IMU offset corrected: the evaluation the
calibrator paper (Avola et al. 2023, section 5) asks for and could not run.

Flights, each simulated with its own constant IMU offset in the physical range (per axis
0.01-0.03 rad/s, 0.05-0.15 m/s^2, random signs; :func:`uavcal_jax.pipeline.drift.physical_offset`)
on top of the simulated ADIS16448's own noise and turn-on bias:

* ``straight``: hover, ``--length`` metres in a line at ``--speed``, stop (1 km at 10 m/s by
  default: about 115 s, 2300 stereo frames);
* ``loop``: a procedural flight of ``--loop-duration`` seconds at up to 5 m/s over a 60 m
  square (:data:`uavcal_jax.pipeline.drift.LOOP_LIMITS`). Its 120 s default (2380 frames,
  about 170 m with its hovers and turns) is as long in time as the line but shorter in
  distance: a 1 km loop at these speeds is about 7000 frames, three times the budget.

Each flight is run with each correction subtracted from its IMU: ``raw`` (none); every
estimator of ``uavcal calib predict`` in ``--methods``, each estimated blind (the ground truth
hidden from it) on the same recording; ``true`` (the true total constant error: the offset plus
the sensor's own bias). Per correction: (a) IMU-only dead reckoning from the true initial state
and (b) the stereo VIO, each scored by the final position error (the VIO first aligned in
heading and origin over its first 10 m), that error as % of the distance flown, and the ATE
(SE(3)-aligned RMSE); :mod:`uavcal_jax.pipeline.drift` does the work.

The VIO self-calibration is among them as ``self-calib``
(:mod:`uavcal_jax.pipeline.self_calib`: the VIO's own windows, biases pinned, descended
through). Session 17's timing below predates it; it adds one VIO pass per flight.

Resolution: 376x240 by default, a quarter of EuRoC's pixels. Per flight the study renders
about 2300 stereo frames and runs the VIO six times over them (once inside ``vio-bias``); on the
shared 2-core CPU at 376x240 a pass runs at 20-30 frames/s once compiled and a render at 12-18,
so the default study took 41 minutes (2470 s). Four times the pixels (EuRoC's 752x480) slows
the front end and the render with them, and would not fit an hour.

Writes ``OUT/drift.md`` (the table), ``OUT/drift.json`` and ``OUT/drift.png`` (error against
distance, dead reckoning and VIO panels per flight); prints the table and, as the last line,
one JSON object (the table's figures, the paths and the wall time).

Usage::

    python experiments/drift_long_flight.py --quick            # a smoke run, a few minutes
    python experiments/drift_long_flight.py --out /work/runs/drift   # the full study
    python experiments/drift_long_flight.py --flights straight --methods vio-bias
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _docs import add_write_docs, write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import parse_resolution, positive, print_json, to_builtin
from uavcal_jax.pipeline.drift import (
    FLIGHT_KINDS,
    RAW,
    TRUE,
    DriftFlight,
    evaluate_recording,
    physical_offset,
    simulate_flight,
)
from uavcal_jax.pipeline.offset_estimators import method_names
from uavcal_jax.plots import plot_drift_curves
from uavcal_jax.sim.config import LOW_RESOLUTION
from uavcal_jax.xla_cache import enable_compilation_cache

ROOT = Path(__file__).resolve().parents[1]
QUICK = {"length": 60.0, "speed": 5.0, "loop_duration": 20.0}


def flights(args) -> list[DriftFlight]:
    out = []
    if "straight" in args.flights:
        out.append(DriftFlight(f"straight_{args.length:g}m_{args.speed:g}mps", "straight",
                               length_m=args.length, speed=args.speed, seed=args.seed))
    if "loop" in args.flights:
        out.append(DriftFlight(f"loop_{args.loop_duration:g}s_seed{args.seed + 1}", "loop",
                               duration_s=args.loop_duration, seed=args.seed + 1))
    return out


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table(results: dict) -> str:
    """The markdown table: one row per flight and correction."""
    lines = ["| flight | correction | offset err gyro RMS (rad/s) | offset err accel RMS (m/s^2) "
             "| DR final (m) | DR ATE (m) | DR final % dist | VIO final (m) | VIO ATE (m) "
             "| VIO final % dist | VIO resets |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for flight, res in results.items():
        for name, row in res["corrections"].items():
            dr, vio = row["dead_reckoning"], row["vio"]
            lines.append(
                f"| {flight} | {name} | {row['gyro_rms']:.2e} | {row['accel_rms']:.2e} "
                f"| {_fmt(dr['final_error_m'], '.3g')} | {_fmt(dr['ate_m'], '.3g')} "
                f"| {_fmt(dr['final_error_pct'], '.3g')} "
                f"| {_fmt(vio['final_error_m'], '.3g')} | {_fmt(vio['ate_m'], '.3g')} "
                f"| {_fmt(vio.get('final_error_pct'), '.3g')} | {vio['resets']} |")
    return "\n".join(lines)


def _without_curves(results: dict) -> dict:
    """JSON-ready results: curves dropped (they are in the PNG), estimator summaries cut to
    their scalars."""
    out = {}
    for flight, res in results.items():
        rows = {}
        for name, row in res["corrections"].items():
            r = {k: v for k, v in row.items() if k not in ("summary",)}
            for part in ("dead_reckoning", "vio"):
                r[part] = {k: v for k, v in row[part].items() if k != "curve"}
            if "summary" in row:
                r["estimate"] = {k: row["summary"].get(k) for k in (
                    "label", "channels", "offset", "true", "error", "rmse", "items")}
            rows[name] = r
        out[flight] = {**{k: v for k, v in res.items() if k != "corrections"},
                       "corrections": rows}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "out" / "drift")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "sim_cache",
                    help="simulated flights, rendered once and reused")
    ap.add_argument("--flights", nargs="+", choices=FLIGHT_KINDS, default=list(FLIGHT_KINDS))
    ap.add_argument("--length", type=positive, default=1000.0, help="straight flight, m")
    ap.add_argument("--speed", type=positive, default=10.0, help="straight flight, m/s")
    ap.add_argument("--loop-duration", type=positive, default=120.0, help="loop, seconds")
    ap.add_argument("--resolution", type=parse_resolution, default=LOW_RESOLUTION,
                    help="WxH of the simulated frames (see the docstring) "
                         f"[{LOW_RESOLUTION[0]}x{LOW_RESOLUTION[1]}]")
    ap.add_argument("--methods", nargs="*", choices=method_names(), default=list(method_names()),
                    help="offset estimators to compare [all]")
    ap.add_argument("--seed", type=int, default=0, help="offsets, loop plan and noise")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run: a 60 m line at 5 m/s and a 20 s loop")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    add_write_docs(ap)
    args = ap.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            setattr(args, key, value)

    enable_compilation_cache()
    t0 = time.perf_counter()
    results = {}
    for k, flight in enumerate(flights(args)):
        offset = physical_offset(args.seed + k)
        rec = simulate_flight(flight, args.cache, offset, resolution=args.resolution,
                              progress=not args.quiet)
        t = time.perf_counter()
        res = evaluate_recording(rec, args.methods, progress=not args.quiet)
        results[flight.name] = {"recording": str(rec), "injected_offset": offset,
                                "seconds": time.perf_counter() - t, **res}
        print(f"{flight.name}: {time.perf_counter() - t:.0f} s", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    text = table(results)
    md = args.out / "drift.md"
    md.write_text(f"{text}\n")
    panels = []
    for flight, res in results.items():
        for part, label in (("dead_reckoning", "dead reckoning"), ("vio", "VIO")):
            lines = {name: (row[part]["curve"]["distance_m"], row[part]["curve"]["error_m"])
                     for name, row in res["corrections"].items()
                     if row[part].get("curve") is not None}
            panels.append((f"{flight}: {label}", lines))
    png = plot_drift_curves(args.out / "drift.png", panels,
                            title="position error against distance travelled")
    summary = _without_curves(results)
    js = args.out / "drift.json"
    js.write_text(json.dumps(json.loads(json.dumps(summary, default=to_builtin)), indent=1))
    print(text)
    write_docs(args, "drift_long_flight", text, argv=argv,
               anchor="the raw IMU and the true offset removed, in the same run")
    wall = time.perf_counter() - t0
    brief = {flight: {name: {"vio_final_m": row["vio"]["final_error_m"],
                             "vio_ate_m": row["vio"]["ate_m"],
                             "dr_final_m": row["dead_reckoning"]["final_error_m"],
                             "gyro_rms": row["gyro_rms"], "accel_rms": row["accel_rms"]}
                      for name, row in res["corrections"].items()}
             for flight, res in summary.items()}
    out = {"table": str(md), "json": str(js), "png": str(png), "wall_s": round(wall, 1),
           "corrections": [RAW, *args.methods, TRUE], "results": brief}
    print_json(out)
    return out



if __name__ == "__main__":
    main()
