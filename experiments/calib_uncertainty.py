"""Measure the scales that make the offset estimators' sigmas standard deviations, on flights
apart from those the tables judge them on (issue 43, item 4).

Each method's recording sigma (:mod:`uavcal_jax.pipeline.offset_uncertainty`) is its items'
batch-means standard error, plus what the items share where the method predicts it. On
simulated flights whose offset is known this script measures, per method and sensor, the
scale that gives the z-scores an RMS of 1:

- ``vio-bias`` gyro and ``visual-ls``: the scale on the whole sigma (``SIGMA_SCALE`` in
  :mod:`uavcal_jax.pipeline.vio_bias` and :mod:`uavcal_jax.pipeline.visual_ls`: copy the
  printed values there); ``vio-bias``'s accelerometer sigma is its alignment's (its own
  ``error_inflation``), reported, not refitted;
- ``transformer``: the share ``k`` of the model's median window sigma that a recording's
  windows have in common (:func:`~uavcal_jax.pipeline.offset_uncertainty.fit_common_scale`);
  ``--write-run`` writes it into the checkpoint's run folder
  (:data:`~uavcal_jax.pipeline.transformer_offset.UNCERTAINTY_FILE`), where the method reads
  it.

The default flights are the 11 EuRoC trajectories from 40 s in, seed 11
(``calib_blind.py``'s tables use 10 s in, seed 7, and the UZH-FPV flights as well).

Usage::

    python experiments/calib_uncertainty.py --cache /work/exp/blind_cache
    python experiments/calib_uncertainty.py --write-run        # the shipped weights' file

The last stdout line is one JSON object; ``OUT/results.json`` holds every row.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
from _calib_common import ROOT  # the script's folder is first on sys.path
from calib_blind import flight_names, simulated_flights

from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.pipeline.offset_estimators import configure_method
from uavcal_jax.pipeline.offset_uncertainty import (
    block_standard_error,
    fit_common_scale,
    fit_scale,
)
from uavcal_jax.pipeline.predict_offset import known_offset, predict_offset, score
from uavcal_jax.pipeline.transformer_offset import run_folder, write_common_scale

#: The sensors' channels in a six-channel row.
SENSOR_AXES = {"gyro": slice(0, 3), "accel": slice(3, 6)}


def _rows(flights: list[Path], methods: list[str], checkpoint, quiet: bool) -> list[dict]:
    rows = []
    for folder in flights:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sequence, _ = read_sequence(folder)
        truth = known_offset(recorded_imu_offset(folder), None)
        for method in methods:
            options = configure_method(method, checkpoint=checkpoint
                                       if method == "transformer" else None)
            summary, estimate = predict_offset(sequence, method, options)
            scored = score(estimate, truth, sequence.ground_truth, all_channels=True)
            row = {"recording": folder.name, "method": method,
                   "channels": list(estimate.channels),
                   "error": np.asarray(scored["error"])[estimate.channel_index].tolist(),
                   "sigma": None if estimate.sigma is None else estimate.sigma.tolist()}
            if method == "transformer" and estimate.sigma is not None:
                row["standard_error"] = block_standard_error(
                    estimate.per_item, estimate.item_t_s,
                    estimate.settings.window.duration).tolist()
                row["window_sigma"] = summary["window_sigma_median"]
            rows.append(row)
            if not quiet:
                print(f"{folder.name} {method}: error {np.round(row['error'], 4).tolist()} "
                      f"sigma {None if row['sigma'] is None else np.round(row['sigma'], 4)}",
                      file=sys.stderr)
    return rows


def _stack(rows: list[dict], key: str, sensor: str) -> np.ndarray:
    at = SENSOR_AXES[sensor]
    return np.array([np.asarray(r[key], np.float64)[at] for r in rows
                     if len(r["channels"]) == 6 or sensor == "gyro"])


def fits(rows: list[dict]) -> dict:
    """Per method and sensor: the z-scores' RMS as measured, and the fitted scale."""
    out: dict = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method and r["sigma"] is not None]
        for sensor in SENSOR_AXES:
            part = [r for r in mine if sensor == "gyro" or len(r["channels"]) == 6]
            if not part:
                continue
            errors, sigma = _stack(part, "error", sensor), _stack(part, "sigma", sensor)
            entry = {"z_rms": fit_scale(errors, sigma), "rows": len(part),
                     "rms_error": float(np.sqrt(np.mean(np.square(errors))))}
            if method == "transformer":
                entry["common_scale"] = fit_common_scale(
                    errors, _stack(part, "standard_error", sensor),
                    _stack(part, "window_sigma", sensor))
            out.setdefault(method, {})[sensor] = entry
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", type=flight_names, default=None,
                    help="trajectory names, comma-separated, or 'all' [default: the 11 EuRoC]")
    ap.add_argument("--start", type=float, default=40.0)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--methods", type=lambda s: [m for m in s.split(",") if m],
                    default=["vio-bias", "visual-ls", "transformer"])
    ap.add_argument("--checkpoint", type=Path, default=None,
                    help="the transformer's run folder [default: the shipped weights]")
    ap.add_argument("--write-run", action="store_true",
                    help="write the transformer's common scale into its run folder")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "calib_cache")
    ap.add_argument("--out", type=Path,
                    default=ROOT / "experiments" / "out" / "calib_uncertainty")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args()
    if args.flights is None:
        args.flights = [n for n in flight_names("all") if n[:2] in ("MH", "V1", "V2")]
    args.imu_rotation = None
    args.out.mkdir(parents=True, exist_ok=True)
    flights = simulated_flights(args)
    rows = _rows(flights, args.methods, args.checkpoint, args.quiet)
    fitted = fits(rows)
    result = {"flights": [f.name for f in flights], "fits": fitted, "rows": rows}
    transformer = fitted.get("transformer")
    if args.write_run and transformer:
        scales = {c: transformer[sensor]["common_scale"]
                  for sensor, axes in (("gyro", "gx gy gz"), ("accel", "ax ay az"))
                  if sensor in transformer for c in axes.split()}
        result["written"] = str(write_common_scale(
            run_folder(args.checkpoint), scales,
            {"command": "python experiments/calib_uncertainty.py " + " ".join(sys.argv[1:]),
             "flights": result["flights"], "start_s": args.start, "duration_s": args.duration,
             "seed": args.seed}))
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({"flights": len(flights), "fits": fitted,
                      "written": result.get("written")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
