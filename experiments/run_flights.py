"""``uavcal run`` on simulated flights past a moving car: the VIO's ATE and the car's error.

Each flight is ``uavcal simulate`` along a real trajectory (EuRoC's, or UZH-FPV's indoor ones
with the rig in FLU and the camera pitched down), 20 s at 752x480 with depth, one car driving
where the camera looks and a constant IMU offset (:data:`IMU_OFFSET`), on the simulator's
defaults (EuRoC's rig: auto-exposure, vignetting, rotor vibration, IMU scale, misalignment
and g-sensitivity; ``--ideal-sensors``: all off). Then ``uavcal run``'s pipeline
(:func:`uavcal_jax.pipeline.run.run_pipeline`, default settings, ``--set`` over them) flies
it three times: with the shipped detector's boxes as they come (``refine.enabled=false``);
with them redrawn around what the depth image shows (``refine.enabled=true``,
:mod:`uavcal_jax.track.depth_box`; ``--no-refined`` skips it); and with the renderer's own
boxes as they come (``labels``: perfect detections, the detector's ceiling; ``--no-labels``
skips it).

Per flight: the VIO's ATE (posyaw-aligned RMSE) and resets, the fraction of frames with the
car detected, and the filtered car's median and RMSE error against the true target under the
followed box (``uavcal run``'s ``target_error_m.filtered``), with the times the target
followed changed from one labelled target to another (``detections.target_switches``; the
scene has other cars and people). The last rows count the flights within 0.5 m (median) and
1 m (RMSE), the switches, and give the means.

Usage::

    python experiments/run_flights.py                        # 15 flights: 20 min, +30 to render
    python experiments/run_flights.py --flights MH_04_difficult indoor_45_4 --no-refined --no-labels
    python experiments/run_flights.py --detector RUN --write-docs candidate

Recordings are cached in ``--cache`` (by their full configuration), runs go to ``--out``.
The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
from _docs import add_write_docs, write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import print_json
from uavcal_jax.config import ConfigError, apply_overrides
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.results_doc import markdown_table
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.detectors import LabelDetector, load_network_detector
from uavcal_jax.pipeline.run import run_pipeline
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim.cache import cached_simulation
from uavcal_jax.sim.config import IDEAL_SENSORS, SimConfig
from uavcal_jax.sim.training_sets import trajectory_dir

ROOT = Path(__file__).resolve().parents[1]
DATA_ROOT = ROOT.parent / "shared" / "data"
#: The IMU offset every flight carries (gyro rad/s xyz, accel m/s^2 xyz).
IMU_OFFSET = (0.02, -0.015, 0.01, 0.08, -0.06, 0.1)
DURATION_S = 20.0
#: Figures the table checks each flight against: the car's filtered median and RMSE, metres.
MEDIAN_BOUND_M, RMSE_BOUND_M = 0.5, 1.0


class Flight(NamedTuple):
    """One flight: a trajectory (``dataset``'s ``name``), where it starts (s), the seed, and
    for UZH-FPV the camera's pitch below the FLU body's forward axis (degrees)."""

    name: str
    dataset: str
    start: float
    seed: int
    pitch_deg: float | None = None


#: Seven EuRoC flights and eight UZH-FPV indoor ones (four forward-looking at 30 degrees,
#: four at 45).
FLIGHTS = (
    Flight("MH_04_difficult", "euroc", 15.0, 11),
    Flight("MH_05_difficult", "euroc", 15.0, 5),
    Flight("V1_01_easy", "euroc", 20.0, 14),
    Flight("V1_02_medium", "euroc", 10.0, 3),
    Flight("V1_03_difficult", "euroc", 10.0, 4),
    Flight("V2_02_medium", "euroc", 10.0, 7),
    Flight("V2_03_difficult", "euroc", 10.0, 12),
    Flight("indoor_forward_5", "uzh_fpv", 5.0, 13, 30.0),
    Flight("indoor_forward_6", "uzh_fpv", 5.0, 13, 30.0),
    Flight("indoor_forward_7", "uzh_fpv", 5.0, 13, 30.0),
    Flight("indoor_forward_10", "uzh_fpv", 5.0, 13, 30.0),
    Flight("indoor_45_2", "uzh_fpv", 5.0, 7, 45.0),
    Flight("indoor_45_4", "uzh_fpv", 5.0, 7, 45.0),
    Flight("indoor_45_12", "uzh_fpv", 5.0, 7, 45.0),
    Flight("indoor_45_13", "uzh_fpv", 5.0, 7, 45.0),
)


def sim_config(flight: Flight, ideal_sensors: bool) -> SimConfig:
    """The flight's simulation (the start moved earlier, and the flight shortened, where the
    file is too short)."""
    path = trajectory_dir(DATA_ROOT, flight.dataset) / f"{flight.name}.txt"
    if not path.is_file():
        raise DataError("no such trajectory file", path)
    stamps = np.loadtxt(path, usecols=0, ndmin=1)
    span = float(stamps[-1] - stamps[0])
    duration = min(DURATION_S, span)
    start = max(0.0, min(flight.start, span - duration))
    frame = {} if flight.pitch_deg is None else {"body_frame": "flu",
                                                  "camera_pitch_deg": flight.pitch_deg}
    config = SimConfig(trajectory=str(path), start=start, duration=duration,
                       seed=flight.seed, follow_targets=1, imu_offset=IMU_OFFSET, **frame)
    return dataclasses.replace(config, **IDEAL_SENSORS) if ideal_sensors else config


def _figures(metrics: dict) -> dict:
    """A run's figures of the table from its ``metrics.json``."""
    car = (metrics.get("target_error_m") or {}).get("filtered") or {}
    ate = metrics.get("ate_m") or {}
    return {"ate_m": ate.get("rmse"), "resets": metrics["vio"]["resets"],
            "detected": metrics["follow"]["fraction_detected"],
            "car_median_m": car.get("median"), "car_rmse_m": car.get("rmse"),
            "switches": metrics["detections"].get("target_switches")}


def fly(flight: Flight, args, config: RunConfig, detector) -> dict:
    """Simulate (cached) and run one flight in each of the table's columns."""
    sim = sim_config(flight, args.ideal_sensors)
    recording = cached_simulation(sim, args.cache, flight.name, progress=not args.quiet)
    read = read_sequence(recording, strict=True)  # the simulator's output needs no repairs
    row = {"flight": flight.name, "start_s": sim.start, "duration_s": sim.duration,
           "seed": flight.seed, "recording": str(recording)}
    for key in columns(args):
        boxes = LabelDetector(read[0].targets) if key == "labels" else detector
        settings = apply_overrides(config, [f"refine.enabled={str(key == 'refined').lower()}"])
        result = run_pipeline(recording, args.out / flight.name / key, settings, read=read,
                              detector=boxes, progress=not args.quiet)
        row[key] = _figures(result.metrics)
    return row


def columns(args) -> tuple[str, ...]:
    """The runs of each flight: ``detector`` (its boxes as they come), ``refined`` (redrawn
    from the depth, ``refine.enabled``), ``labels`` (the renderer's boxes, as they come)."""
    return ("detector",) + (() if args.no_refined else ("refined",)) \
        + (() if args.no_labels else ("labels",))


def _metres(value) -> str:
    return "—" if value is None else f"{value:.2f}"


def _car(fig: dict) -> str:
    switches = fig.get("switches") or 0
    return f"{_metres(fig['car_median_m'])} / {_metres(fig['car_rmse_m'])}" + (
        f" ({switches} switch{'es' if switches > 1 else ''})" if switches else "")


def _within(fig: dict) -> bool:
    return (fig["car_median_m"] is not None and fig["car_median_m"] <= MEDIAN_BOUND_M
            and fig["car_rmse_m"] <= RMSE_BOUND_M)


def summary(rows: list[dict], key: str) -> dict:
    """Means and counts over the flights of one detector column."""
    figs = [r[key] for r in rows if key in r]
    values = {k: [f[k] for f in figs if f[k] is not None]
              for k in ("ate_m", "car_median_m", "car_rmse_m", "detected")}
    return {"flights": len(figs), "within": sum(_within(f) for f in figs),
            "switches": sum(f.get("switches") or 0 for f in figs),
            **{f"mean_{k}": float(np.mean(v)) if v else None for k, v in values.items()}}


#: The table's heading of each column.
COLUMN_TITLES = {"detector": "car: median / RMSE (m)",
                 "refined": "boxes redrawn from depth: median / RMSE (m)",
                 "labels": "renderer's boxes: median / RMSE (m)"}


def table(rows: list[dict], keys: tuple[str, ...]) -> str:
    """The markdown table: a row per flight, then the means and the count within bounds."""
    head = ["flight", "ATE (m)", "resets", "car detected"] + [COLUMN_TITLES[k] for k in keys]
    body = []
    for r in rows:
        d = r["detector"]
        span = f"{r['start_s']:g}-{r['start_s'] + r['duration_s']:g} s"
        body.append([f"{r['flight']} {span}", _metres(d["ate_m"]), str(d["resets"]),
                     f"{100 * d['detected']:.0f} %"] + [_car(r[k]) for k in keys])
    s = {k: summary(rows, k) for k in keys}
    detected = s["detector"]["mean_detected"]
    body.append([f"mean of {len(rows)}", _metres(s["detector"]["mean_ate_m"]), "",
                 "—" if detected is None else f"{100 * detected:.0f} %"]
                + [f"{_metres(s[k]['mean_car_median_m'])} / {_metres(s[k]['mean_car_rmse_m'])}"
                   for k in keys])
    body.append([f"within {MEDIAN_BOUND_M:g} / {RMSE_BOUND_M:g} m", "", "", ""]
                + [f"{s[k]['within']} of {s[k]['flights']}, {s[k]['switches']} switches"
                   for k in keys])
    return markdown_table(head, body)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", nargs="+", default=None, metavar="NAME",
                    help=f"a subset of {[f.name for f in FLIGHTS]}")
    ap.add_argument("--detector", type=Path, default=None, metavar="RUN",
                    help="a `uavcal detect train` run folder [default: the shipped weights]")
    ap.add_argument("--no-refined", action="store_true",
                    help="skip the runs with the boxes redrawn from the depth")
    ap.add_argument("--no-labels", action="store_true",
                    help="skip the runs on the renderer's boxes")
    ap.add_argument("--ideal-sensors", action="store_true",
                    help="simulate with every realism effect off (sim.config's IDEAL_SENSORS)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="RunConfig fields over the defaults (as `uavcal run --set`)")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "run_cache",
                    help="simulated recordings [default: %(default)s]")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "out" / "run_flights",
                    help="the runs' folders [default: %(default)s]")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    add_write_docs(ap)
    args = ap.parse_args()
    known = {f.name: f for f in FLIGHTS}
    unknown = [n for n in args.flights or () if n not in known]
    if unknown:
        ap.error(f"--flights: unknown {unknown}; choose from {list(known)}")
    flights = [known[n] for n in args.flights] if args.flights else list(FLIGHTS)
    try:
        config = apply_overrides(RunConfig(), args.set)
        detector = load_network_detector(args.detector, config.detect.detector_threshold(),
                                         config.detect.tile_config())
    except (ConfigError, DataError) as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    t0 = time.perf_counter()
    rows = []
    for flight in progress_bar(flights, desc="flights", enabled=not args.quiet, unit="flight"):
        try:
            rows.append(fly(flight, args, config, detector))
        except DataError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)
    text = table(rows, columns(args))
    print(text)
    detector_name = "shipped" if args.detector is None else str(args.detector)
    write_docs(args, "run_flights", text, anchor=(
        f"detector: {detector_name}; sensors: "
        f"{'ideal' if args.ideal_sensors else 'the realistic defaults'}; the renderer's own "
        "boxes (labels) are the detector's ceiling"))
    print_json({"flights": rows, "detector": detector_name, "ideal_sensors": args.ideal_sensors,
                "set": args.set, "summary": {k: summary(rows, k) for k in columns(args)},
                "seconds": time.perf_counter() - t0})


if __name__ == "__main__":
    main()
