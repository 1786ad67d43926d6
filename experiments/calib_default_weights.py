"""Make the small calibrator weights shipped in the package (``uavcal demo``, ``uavcal calib
predict --method transformer`` without ``--checkpoint``).

Recipe: ``--flights`` seeded procedural flights of ``--duration`` s at the demo's resolution
(:data:`uavcal_jax.sim.config.LOW_RESOLUTION`), each with a real multirotor's airframe
(``--airframes realistic``: rotor drag, thrust-axis tilt, IMU mounting tilt), rendered once
into ``--cache``
(:mod:`uavcal_jax.sim.training_sets`); trained on them (what ``uavcal calib train`` runs) with
the ``shipped`` preset (:data:`uavcal_jax.calib.presets.PRESETS`: ``small``'s 160x96 frames in
32x32 patches, d 64, pre-norm, AdamW 1e-3, with the physical injection protocol -- offsets in
the range of real IMU biases, like the demo's -- and its ``total`` label, the motion tokens of
the front end's visual rotations (computed once per flight and cached beside it) with the gyro
head starting at their least squares, an uncertainty head (``model.variance``), and 2 s
windows at the full 20 Hz), a fifth of the
flights held out for validation, early stopping on the validation loss; then the run's
``config.json`` and best checkpoint (optimiser moments dropped,
:func:`uavcal_jax.calib.loop.export_weights`) go to
:data:`uavcal_jax.calib.pretrained.DEFAULT_WEIGHTS` (with ``--install``).

The shipped weights are the trained run with its learned correction switched off
(``--closed-form-only DIR``; :mod:`uavcal_jax.calib.pretrained` says why), their uncertainty
scale measured after (``calib_uncertainty.py --write-run``).

Usage::

    python experiments/calib_default_weights.py --closed-form-only uavcal_jax/calib/weights/demo
    python experiments/calib_default_weights.py --install          # the run as trained
    python experiments/calib_default_weights.py --flights 4 --epochs 2   # a smoke run

Prints the training summary and, as the last line, one JSON object (validation metrics of
the best epoch beside the mean-offset baseline, sizes, wall time).
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from uavcal_jax.argtypes import positive, positive_int, print_json
from uavcal_jax.calib.data import load_windows
from uavcal_jax.calib.loop import export_weights, fit
from uavcal_jax.calib.presets import PRESETS, resolve_configs
from uavcal_jax.calib.pretrained import DEFAULT_WEIGHTS
from uavcal_jax.pipeline.motion_inputs import folder_sources
from uavcal_jax.sim.config import LOW_RESOLUTION
from uavcal_jax.sim.training_sets import AIRFRAMES, SimSetConfig, simulated_set

ROOT = Path(__file__).resolve().parents[1]
#: The shipped model's preset (``uavcal calib train --preset shipped``).
PRESET = "shipped"
#: Seed of the procedural flights (the demo flies seed 0: training starts past it).
FLIGHT_SEED = 1000


def _size_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", type=positive_int, default=24, help="procedural flights")
    ap.add_argument("--duration", type=positive, default=20.0, help="seconds per flight")
    ap.add_argument("--epochs", type=positive_int, default=PRESETS[PRESET].train.epochs,
                    help="most epochs [default: the preset's, %(default)s]")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "calib_cache")
    ap.add_argument("--run", type=Path, default=ROOT / "experiments" / "out" / "calib_default")
    ap.add_argument("--install", action="store_true",
                    help=f"copy the best checkpoint to {DEFAULT_WEIGHTS}")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="override the preset (e.g. the IMU-only reference of calib_blind.py: "
                         "model.use_video=false model.motion_tokens=false "
                         "model.closed_form=none window.rotations=none)")
    ap.add_argument("--airframes", choices=AIRFRAMES, default="realistic",
                    help="the procedural flights' airframes (SimSetConfig.airframes): "
                         "'realistic' draws each flight's rotor drag, thrust-axis tilt and IMU "
                         "mounting tilt; 'ideal' flies the thrust exactly along a + g "
                         "[default: %(default)s]")
    ap.add_argument("--closed-form-only", type=Path, default=None, metavar="DIR",
                    help="also export the trained run with its learned correction switched off "
                         "(the head's weights zeroed: the closed form alone) to DIR")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args()
    t0 = time.perf_counter()
    folders = simulated_set(SimSetConfig(family="procedural", count=args.flights,
                                         max_duration=args.duration,
                                         resolution=LOW_RESOLUTION, seed=FLIGHT_SEED,
                                         airframes=args.airframes),
                            args.cache, progress=not args.quiet)
    t_sim = time.perf_counter() - t0
    run = resolve_configs(args.set, preset=PRESET, epochs=args.epochs)
    config, loop, window = run.calib, run.loop, run.window
    # whole flights held out (overlapping windows of one flight share frames: a split over
    # windows would validate on frames it trained on)
    parts = load_windows(folders, window, **folder_sources(window))
    n_val = max(1, round(loop.val_fraction * len(parts)))
    train, val = parts[:-n_val], parts[-n_val:]
    shutil.rmtree(args.run, ignore_errors=True)
    inputs = {"action": "experiments/calib_default_weights.py", "preset": PRESET,
              "flights": args.flights, "duration": args.duration, "flight_seed": FLIGHT_SEED,
              "airframes": args.airframes, "set": args.set}
    res = fit(config, train, val, args.run, loop=loop, progress=not args.quiet,
              inputs=inputs).summary
    best = res["best"]
    summary = {"flights": args.flights, "duration_s": args.duration, "preset": PRESET,
               "windows": {"train": res["num_train"], "val": res["num_val"]},
               "epochs_run": res["epochs"], "best_epoch": res["best_epoch"],
               "val_offset_rmse": best.get("val_offset_rmse"),
               "val_sign_f1": best.get("val_sign_f1"),
               "val_z_rms": best.get("val_z_rms"),
               "baseline_offset_rmse": best.get("baseline_offset_rmse"),
               "window_mean_offset_rmse": best.get("window_mean_offset_rmse"),
               "simulate_s": round(t_sim, 1), "wall_s": round(time.perf_counter() - t0, 1),
               "command": "python experiments/calib_default_weights.py " + " ".join(
                   f"--{k} {getattr(args, k)}" for k in ("flights", "duration", "epochs",
                                                         "airframes"))
               + (" --set " + " ".join(args.set) if args.set else "")}
    if args.closed_form_only is not None:  # the credit-assignment twin: no learned part
        summary["closed_form_only"] = str(export_weights(args.run, args.closed_form_only,
                                                         train, closed_form_only=True))
    if args.install:
        target = export_weights(args.run, DEFAULT_WEIGHTS, train)
        summary.update(installed=str(target), installed_bytes=_size_bytes(target))
    print_json(summary)


if __name__ == "__main__":
    main()
