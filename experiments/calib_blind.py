"""The IMU offset estimators that need no ground truth, on flights they have never seen and on
a real IMU: the tables behind issue 20's checks (``uavcal calib predict --method``).

Recordings:

- **simulated flights** along real EuRoC trajectories (``--flights``, ``--start``,
  ``--duration``), each with its own physical-range constant offset injected into the IMU
  (per axis uniform in +-0.08 rad/s and +-0.16 m/s^2, the calibrator's physical protocol,
  drawn from ``--seed``); the simulated IMU adds its own turn-on bias and random walk;
- **the hybrid V1_01 recording** (``--hybrid``): the real V1_01 IMU and ground truth
  (``../shared/data/euroc_v101_micro``) with frames rendered along the real trajectory
  (:func:`uavcal_jax.sim.hybrid.simulate_hybrid`); its truth is the real sensor's bias from
  EuRoC's ground-truth estimate.

Each method (``--methods``) estimates the constant to subtract without the ground truth
(:func:`uavcal_jax.pipeline.offset_scores.score_recordings`); the truth is the ``total``
label (the injected offset plus the sensor's own bias over the span the method used). The
table pools the simulated flights (RMS error per axis, per sensor, sign F1) beside no
correction, and gives the hybrid's errors per axis. Recordings are rendered into ``--cache``
once.

Usage::

    python experiments/calib_blind.py                          # 3 flights + hybrid, ~30 min
    python experiments/calib_blind.py --flights MH_04_difficult --duration 20 --no-hybrid
    python experiments/calib_blind.py --checkpoint imu-only=runs/imu_only   # a reference row
    python experiments/calib_blind.py --imu-rotation=0,-90,0 --no-hybrid  # another mounting

Writes ``OUT/table.md`` and ``OUT/results.json``; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from _calib_common import ROOT, SHARED_DATA  # the script's folder is first on sys.path
from _docs import add_write_docs, write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import parse_vector3
from uavcal_jax.calib.config import InjectionConfig
from uavcal_jax.data.tum import read_tum
from uavcal_jax.pipeline.offset_estimators import (
    DEFAULT_METHOD,
    configure_method,
    method_names,
)
from uavcal_jax.pipeline.offset_scores import NO_CORRECTION, pooled_scores, score_recordings
from uavcal_jax.sim.cache import cached_simulation, config_tag
from uavcal_jax.sim.config import SimConfig

#: EuRoC trajectories held out of the shipped calibrator's training (calib_default_weights.py
#: trains on procedural flights) and of the tests.
DEFAULT_FLIGHTS = ("MH_04_difficult", "V1_03_difficult", "V2_02_medium")
MICRO = SHARED_DATA / "euroc_v101_micro"
#: The trajectory folders ``--flights`` names are looked up in, in order, with their files'
#: body frame (``SimConfig.body_frame``): UZH-FPV's is a quadrotor's (x forward, z up), on
#: which EuRoC's IMU is mounted as on EuRoC's MAV.
TRAJECTORY_SETS = {"euroc": "euroc", "uzh_fpv": "flu"}


def physical_offsets(n: int, seed: int) -> np.ndarray:
    """``(n, 6)`` offsets, per axis uniform in the physical protocol's ranges."""
    inj = InjectionConfig()
    bound = np.array([inj.gyro_range] * 3 + [inj.accel_range] * 3)
    return np.random.default_rng(seed).uniform(-bound, bound, size=(n, 6))


def trajectory_file(name: str) -> tuple[Path, str]:
    """The TUM file of trajectory ``name`` among :data:`TRAJECTORY_SETS`, and its body
    frame."""
    for folder, body_frame in TRAJECTORY_SETS.items():
        path = SHARED_DATA / "trajectories" / folder / f"{name}.txt"
        if path.is_file():
            return path, body_frame
    raise SystemExit(f"no trajectory {name!r} in {SHARED_DATA / 'trajectories'} "
                     f"({', '.join(TRAJECTORY_SETS)})")


def flight_names(text: str) -> list[str]:
    """``--flights``: comma-separated names, or ``all`` (every trajectory of
    :data:`TRAJECTORY_SETS` present)."""
    if text != "all":
        return [f for f in text.split(",") if f]
    return sorted(p.stem for folder in TRAJECTORY_SETS
                  for p in (SHARED_DATA / "trajectories" / folder).glob("*.txt"))


def clipped_span(path: Path, start: float, duration: float) -> tuple[float, float]:
    """``(start, duration)`` fitted into the trajectory (the UZH-FPV flights last 19-67 s):
    the start moved earlier (not below 0), then the duration cut to what is left."""
    length = float(np.ptp(read_tum(path).t_ns)) * 1e-9 - 0.05
    start = max(0.0, min(start, length - duration))
    return start, min(duration, length - start)


def simulated_flights(args) -> list[Path]:
    """The folders of ``args.flights`` simulated (``start``, ``duration``, ``seed``,
    ``imu_rotation``, ``cache``, ``quiet``), each with its own physical-range offset."""
    offsets = physical_offsets(len(args.flights), args.seed)
    out = []
    for name, offset in zip(args.flights, offsets, strict=True):
        path, body_frame = trajectory_file(name)
        start, duration = clipped_span(path, args.start, args.duration)
        config = SimConfig(trajectory=str(path), start=start, duration=duration, seed=args.seed,
                           body_frame=body_frame,
                           imu_offset=tuple(float(v) for v in offset), targets=False,
                           imu_rotation_deg=args.imu_rotation)
        out.append(cached_simulation(config, args.cache, name, progress=not args.quiet))
    return out


def _hybrid(args) -> Path:
    from uavcal_jax.sim.hybrid import simulate_hybrid

    config = SimConfig(start=0.0, duration=args.hybrid_duration, seed=args.seed,
                       targets=False)
    folder = args.cache / f"hybrid_V1_01_{config_tag(config)}"
    if not (folder / "sim_config.json").is_file():
        simulate_hybrid(MICRO, folder, config, overwrite=True, progress=not args.quiet)
    return folder


def _named_run(text: str) -> tuple[str, Path]:
    name, sep, run = text.partition("=")
    if not sep or not name or not run:
        raise SystemExit(f"--checkpoint wants NAME=RUN, got {text!r}")
    return name, Path(run)


def _score(recordings: list[Path], methods: list[str], extra: dict[str, Path], args
           ) -> list[dict]:
    """``score_recordings`` of ``methods``, then of the transformer method with each
    ``extra`` run, its rows named after it."""
    rows = score_recordings(recordings, methods, progress=not args.quiet)
    for name, run in extra.items():
        options = {"transformer": configure_method("transformer", checkpoint=run)}
        rows += [{**r, "method": name} for r in score_recordings(
            recordings, ["transformer"], options=options, progress=not args.quiet)]
    return rows


def _fmt(v) -> str:
    return "" if v is None else f"{v:.4f}"


def auto_against_best(pooled: dict) -> dict[str, dict]:
    """Per channel ``auto`` estimates: its RMS error beside the best single method's (by RMS
    error over the same recordings; ``auto`` and :data:`NO_CORRECTION` left out)."""
    if "auto" not in pooled:
        return {}
    out = {}
    for channel, value in pooled["auto"]["rmse"].items():
        singles = {m: s["rmse"][channel] for m, s in pooled.items()
                   if m not in ("auto", NO_CORRECTION) and channel in s["rmse"]}
        if singles:
            best = min(singles, key=singles.get)
            out[channel] = {"auto": value, "best": best, "best_rmse": singles[best]}
    return out


def _auto_lines(pooled: dict) -> list[str]:
    versus = auto_against_best(pooled)
    if not versus:
        return []
    return ["", "`auto` per channel against the best single method (RMS error): " + "; ".join(
        f"{c} {v['auto']:.4f} vs {v['best']} {v['best_rmse']:.4f}" for c, v in versus.items())
        + "."]


def _table(pooled: dict, hybrid_rows: list[dict], args) -> str:
    mount = ("" if args.imu_rotation is None else
             f"; IMU turned by {','.join(f'{v:g}' for v in args.imu_rotation)} deg")
    lines = [f"## Simulated flights along real trajectories ({', '.join(args.flights)}; "
             f"{args.duration:g} s from {args.start:g} s; physical-range offsets, seed "
             f"{args.seed}{mount}), total label", "",
             "| method | gyro RMSE (rad/s) | accel RMSE (m/s^2) | sign F1 | per axis |",
             "| --- | --- | --- | --- | --- |"]
    for method, s in pooled.items():
        axes = ", ".join(f"{c} {v:.4f}" for c, v in s["rmse"].items())
        z = "; ".join(f"z-scores' RMS {sensor} {s[f'{sensor}_z_rms']:.2f}"
                      for sensor in ("gyro", "accel") if s.get(f"{sensor}_z_rms") is not None)
        z = f"; {z}" if z else ""
        lines.append(f"| {method} | {_fmt(s['gyro_rmse'])} | {_fmt(s['accel_rmse'])} | "
                     f"{s['sign_f1']:.3f} | {axes}{z} |")
    lines += _auto_lines(pooled)
    if hybrid_rows:
        lines += ["", f"## Hybrid V1_01 (real IMU, {args.hybrid_duration:g} s): error against "
                  "the real sensor's bias (EuRoC ground-truth estimate)", "",
                  "| method | " + " | ".join(("gx", "gy", "gz", "ax", "ay", "az")) + " |",
                  "| --- |" + " --- |" * 6]
        for r in hybrid_rows:
            err = dict(zip(r["channels"], r["error"], strict=True))
            lines.append(f"| {r['method']} | " + " | ".join(
                _fmt(err.get(c)) for c in ("gx", "gy", "gz", "ax", "ay", "az")) + " |")
        true = dict(zip(hybrid_rows[0]["channels"], hybrid_rows[0]["true"], strict=True))
        lines.append(f"| {NO_CORRECTION} | " + " | ".join(
            _fmt(None if true.get(c) is None else -true[c])
            for c in ("gx", "gy", "gz", "ax", "ay", "az")) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", type=flight_names, default=list(DEFAULT_FLIGHTS),
                    help="EuRoC or UZH-FPV trajectory names, comma-separated, or 'all' (the "
                         "22 of both sets) [default: %(default)s]")
    ap.add_argument("--start", type=float, default=10.0,
                    help="seconds into each trajectory (earlier where the flight is shorter)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds per flight")
    ap.add_argument("--seed", type=int, default=7, help="offsets, IMU noise and scenes")
    ap.add_argument("--imu-rotation", type=parse_vector3, default=None, metavar="RX,RY,RZ",
                    help="turn the simulated flights' IMU on the airframe by this rotation "
                         "vector, degrees (uavcal simulate --imu-rotation: another drone's "
                         "mounting; 0,-90,0 puts gravity on z) [default: EuRoC's mounting]")
    ap.add_argument("--no-hybrid", dest="hybrid", action="store_false",
                    help="leave out the real-IMU hybrid V1_01 recording")
    ap.add_argument("--hybrid-duration", type=float, default=40.0)
    ap.add_argument("--methods", type=lambda s: [m for m in s.split(",") if m],
                    default=None, help=f"comma-separated methods [default: all: "
                    f"{', '.join(method_names())}; {DEFAULT_METHOD} is the default one]")
    ap.add_argument("--checkpoint", action="append", default=[], metavar="NAME=RUN",
                    help="also score the transformer method with the trained run RUN, as row "
                         "NAME (repeatable); e.g. the IMU-only reference: "
                         "imu-only=RUN from calib_default_weights.py --set "
                         "model.use_video=false model.motion_tokens=false "
                         "model.closed_form=none window.rotations=none")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "calib_cache")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "out" / "calib_blind")
    ap.add_argument("--quiet", action="store_true")
    add_write_docs(ap)
    args = ap.parse_args()
    methods = args.methods or list(method_names())
    args.out.mkdir(parents=True, exist_ok=True)

    extra = dict(_named_run(text) for text in args.checkpoint)
    flights = simulated_flights(args)
    rows = _score(flights, methods, extra, args)
    pooled = pooled_scores(rows)
    hybrid_rows = []
    if args.hybrid and MICRO.is_dir():
        hybrid_rows = _score([_hybrid(args)], methods, extra, args)
    # the rows first: they took the time; the table is made from them
    result = {"flights": [str(f) for f in flights], "methods": methods, "rows": rows,
              "pooled": pooled, "hybrid": hybrid_rows,
              "auto_against_best": auto_against_best(pooled),
              "settings": {k: (str(v) if isinstance(v, Path) else v)
                           for k, v in vars(args).items()}}
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    table = _table(pooled, hybrid_rows, args)
    (args.out / "table.md").write_text(table)
    print(table)
    write_docs(args, "calib_blind", table, anchor="no correction (the raw IMU's offset error)")
    print(json.dumps({"pooled": pooled, "hybrid": hybrid_rows}))


if __name__ == "__main__":
    sys.exit(main())
