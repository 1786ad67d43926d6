"""Make the small detector weights shipped in the package (``uavcal run`` without
``--detector``: :func:`uavcal_jax.detect.default_weights.default_detector_run`).

Recipe, four sources joined into one set (:func:`uavcal_jax.detect.datasets.concat_datasets`):

* real aerial photos, :data:`AERIAL` (``--aerial``): the fixed split by image of
  :func:`aerial_split` (the held-out 20 % never trained on), each training photo
  ``--aerial-repeats`` times per epoch (each copy a different crop);
* real photos with neither cars nor people, :data:`NEGATIVES` (``--negatives``);
* the simulator's targets (car, person) on cam0 frames rendered at EuRoC's 752x480 with its
  camera model (exposure, noise, motion blur), ``--rate`` frames a second, along
  ``--procedural`` seeded procedural flights of ``--duration`` s (seeds from
  :data:`FLIGHT_SEED`: the demo flies seed 0, training starts past it), ``--steep`` more with
  the rig pitched :data:`STEEP_PITCH_DEG` down, the EuRoC trajectories :data:`EUROC_TRAIN`
  and the UZH-FPV indoor ones :data:`UZH_TRAIN` (``--body-frame flu``, the rig pitched
  :data:`UZH_PITCH_DEG` down), from :data:`TRAJ_START_S` s in, each with
  :data:`FOLLOW_TARGETS` moving targets placed where the camera looks;
* with ``--low-res``, the same flights again at the fast size :data:`LOW_RESOLUTION` that
  the demo and the closed-loop studies render at (upscaled into the detector's input: softer
  edges than any 752x480 frame gives);
* ``--nadir`` colour frames looking straight down on rendered streets
  (:func:`uavcal_jax.sim.nadir_set.nadir_street_set`, :data:`NADIR_ALTITUDE`).

Rendered data goes once into ``--cache``. Training uses the
:data:`~uavcal_jax.detect.default_weights.SHIPPED` preset (YZNet-YOLO-tiny predicting at
480x640, trained on multi-scale 320x320 crops, YOLOv5's SGD recipe; ``--epochs``, ``--set``)
into ``--cache/run``; a tenth of the rendered frames and the aerial photos' held-out split
validate and choose the best epoch. Training stops early when ``--budget`` minutes have gone
(the epoch that would pass it is not started). The best checkpoint is exported as it ships
(parameters stored as float16, :data:`PARAMS_DTYPE`; restored as float32), scored on each
source by :func:`uavcal_jax.pipeline.detector_sources.score_sources` (a held-out rendered
flight, :data:`HELD_OUT`; the aerial photos' held-out split, whole and sliced; the real EuRoC
frames' false positives), and
written atomically with those scores as ``eval.json`` to ``--out``
(:func:`uavcal_jax.detect.run.export_run`).

Usage::

    python experiments/detector_default_weights.py                 # about 40 min, 2 cores
    python experiments/detector_default_weights.py --init uavcal_jax/detect/weights/default \
        --rate 2 --aerial-repeats 6 --epochs 8 \
        --set train.lr=0.002 train.warmup_bias_lr=0.002   # fine-tune the shipped weights
    python experiments/detector_default_weights.py --init uavcal_jax/detect/weights/default \
        --rate 1.5 --low-res --aerial-repeats 6 --epochs 6 \
        --set train.lr=0.002 train.warmup_bias_lr=0.002   # the last fine-tune, 30 min
    python experiments/detector_default_weights.py --procedural 1 --steep 0 --euroc-flights 0 \
        --uzh-flights 0 --duration 2 --epochs 1 --max-steps 2 --nadir 2 --aerial-repeats 1 \
        --out /tmp/det_smoke --cache /tmp/det_smoke_cache   # smoke, about 3 min

The last line printed is one JSON object: the figures per source and on the validation set,
the weights' size, the set's flights and images, the training and total seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from _docs import (  # the script's folder is first on sys.path
    add_write_docs,
    figures_table,
    write_docs,
)

from uavcal_jax.argtypes import positive, positive_int, print_json
from uavcal_jax.config import apply_overrides
from uavcal_jax.detect.datasets import concat_datasets, load_dataset, split_ids
from uavcal_jax.detect.default_weights import DEFAULT_DETECTOR_RUN, SHIPPED
from uavcal_jax.detect.run import RunPaths, export_run
from uavcal_jax.detect.train import train
from uavcal_jax.pipeline.detector_sources import score_sources
from uavcal_jax.plots import training_curves_writer
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim.cache import cached_simulation
from uavcal_jax.sim.config import LOW_RESOLUTION, SimConfig
from uavcal_jax.sim.nadir_set import nadir_street_set
from uavcal_jax.sim.training_sets import trajectory_dir
from uavcal_jax.xla_cache import enable_compilation_cache

ROOT = Path(__file__).resolve().parents[1]
DATA_ROOT = ROOT.parent / "shared" / "data"
#: First seed of the procedural flights (the demo flies seed 0).
FLIGHT_SEED = 2000
#: The rig's pitch below forward on the ``--steep`` procedural flights, degrees: targets seen
#: from steeply above, as from a low flight with a camera pitched down (UZH-FPV's 45-degree
#: rig); EuRoC's rig looks 20 degrees down.
STEEP_PITCH_DEG = 45.0
#: EuRoC trajectories trained on (MH_04_difficult and V2_03_difficult stay held out).
EUROC_TRAIN = ("MH_01_easy", "V1_02_medium", "MH_03_medium", "V2_01_easy", "V1_03_difficult",
               "MH_05_difficult", "V2_02_medium", "MH_02_easy", "V1_01_easy")
#: UZH-FPV indoor trajectories trained on, flown with ``body_frame="flu"``.
UZH_TRAIN = ("indoor_forward_3", "indoor_45_2", "indoor_45_13", "indoor_forward_7",
             "indoor_forward_9", "indoor_45_14")
#: The UZH-FPV flights' rig pitch below forward, degrees: the 45-degree flights' as recorded
#: (their followed car is seen from steeply above), the forward racers' 30 (their real camera
#: looks at the horizon and sees no floor target).
UZH_PITCH_DEG = {"indoor_45": 45.0, "indoor_forward": 30.0}
#: Seconds into a trajectory file where its flight starts (EuRoC's MAV is still on the
#: ground before), or earlier where the file would end first.
TRAJ_START_S = 20.0
#: Moving targets placed in view of every flight.
FOLLOW_TARGETS = 2
#: How the shipped parameters are stored (:func:`uavcal_jax.detect.run.export_run`).
PARAMS_DTYPE = "float16"
#: The held-out flight: (name, trajectory stem or None, seed), rendered at its own rate
#: (frames a second) and length (s), whatever the training flights'.
HELD_OUT = ("MH_04_difficult", "MH_04_difficult", 9000)
HELD_OUT_RATE, HELD_OUT_DURATION = 2.0, 20.0
#: Real aerial photos (a YOLO folder; its trucks, buses and minibuses are ``car`` through
#: :data:`uavcal_jax.detect.datasets.CLASS_ALIASES`), with the fixed split by image of
#: ``detect_aerial.py`` (:func:`~uavcal_jax.detect.datasets.split_ids`, this fraction, seed 0)
#: holding out the photos scored as "the real aerial set's held-out split".
AERIAL = DATA_ROOT / "detection" / "aerial_cars_kit"
AERIAL_VAL_FRACTION = 0.2
#: Copies of each real aerial training photo per epoch (each a different random crop): the
#: photos are few but large and dense, the rendered frames many.
AERIAL_REPEATS = 16
#: Real photos with neither cars nor people (their own labels, raccoons, are dropped): what a
#: real camera shows that is not a target.
NEGATIVES = DATA_ROOT / "detection" / "raccoon_voc"
#: Nadir colour frames over rendered streets (:func:`uavcal_jax.sim.nadir_set.nadir_street_set`):
#: how many, their first seed, and the altitudes (metres; up to about the real aerial photos'
#: 13 cm ground sample distance at the 1280x720, 70-degree camera).
NADIR_FRAMES, NADIR_SEED, NADIR_ALTITUDE = 80, 7000, (20.0, 130.0)
#: The real EuRoC frames scored for false positives (a room with no car and no person).
MICRO = DATA_ROOT / "euroc_v101_micro"


class _BudgetSpent(Exception):
    """Raised by the per-epoch callback when the next epoch would pass ``--budget``."""


def _optional_dir(text: str) -> Path | None:
    return None if text.lower() == "none" else Path(text)


def _sim(rate: float, duration: float, seed: int, **kw) -> SimConfig:
    return SimConfig(duration=duration, seed=seed, camera_rate_hz=rate, depth=False,
                     follow_targets=FOLLOW_TARGETS, **kw)


def flights(args) -> list[tuple[str, SimConfig]]:
    """``(name, SimConfig)`` of the training flights."""
    out = [(f"proc_{i:02d}", _sim(args.rate, args.duration, FLIGHT_SEED + i))
           for i in range(args.procedural)]
    out += [(f"steep_{i:02d}", _sim(args.rate, args.duration, FLIGHT_SEED + 300 + i,
                                    camera_pitch_deg=STEEP_PITCH_DEG))
            for i in range(args.steep)]
    for i, stem in enumerate(EUROC_TRAIN[:args.euroc_flights]):
        out.append((stem, _sim(args.rate, args.duration, FLIGHT_SEED + 100 + i,
                               trajectory=str(trajectory_dir(DATA_ROOT, "euroc") / f"{stem}.txt"),
                               start=TRAJ_START_S)))
    for i, stem in enumerate(UZH_TRAIN[:args.uzh_flights]):
        path = trajectory_dir(DATA_ROOT, "uzh_fpv") / f"{stem}.txt"
        stamps = np.loadtxt(path, usecols=0, ndmin=1)
        start = max(0.0, min(TRAJ_START_S, float(stamps[-1] - stamps[0]) - args.duration))
        out.append((stem, _sim(args.rate, args.duration, FLIGHT_SEED + 200 + i,
                               trajectory=str(path), start=start, body_frame="flu",
                               camera_pitch_deg=UZH_PITCH_DEG[stem.rsplit("_", 1)[0]])))
    if args.low_res:  # the same flights again at the fast size the demo renders at
        out += [(f"{name}_low", dataclasses.replace(cfg, resolution=LOW_RESOLUTION))
                for name, cfg in out]
    return out


def held_out() -> tuple[str, SimConfig]:
    """``(name, SimConfig)`` of the held-out flight."""
    name, stem, seed = HELD_OUT
    traj = None if stem is None else str(trajectory_dir(DATA_ROOT, "euroc") / f"{stem}.txt")
    return name, _sim(HELD_OUT_RATE, HELD_OUT_DURATION, seed, trajectory=traj,
                      start=TRAJ_START_S if traj else 0.0)


def nadir_frames(cache: Path, n: int) -> Path:
    """The ``n`` nadir street frames, rendered once into ``cache``."""
    folder = cache / f"nadir_{n}_{NADIR_SEED}"
    if not (folder / "nadir_set.json").is_file():
        tmp = folder.with_name(f".{folder.name}.partial")
        shutil.rmtree(tmp, ignore_errors=True)
        nadir_street_set(tmp, n, NADIR_SEED, altitude=NADIR_ALTITUDE)
        shutil.rmtree(folder, ignore_errors=True)
        tmp.rename(folder)
    return folder


def aerial_split(folder: Path, classes):
    """The real aerial photos of ``folder`` (YOLO, in ``classes``) split by image into
    ``(train, held_out)`` (:data:`AERIAL_VAL_FRACTION`, seed 0: ``detect_aerial.py``'s)."""
    aerial = load_dataset(folder, "yolo", classes)
    train_ids, held_out_ids = split_ids(aerial.image_ids, AERIAL_VAL_FRACTION, 0)
    return aerial.subset(train_ids), aerial.subset(held_out_ids)


def training_sets(args, folders, train_cfg):
    """``(train, validation, aerial held-out)`` sets: the rendered flights split by frame
    (``train_cfg.val_fraction``), the real aerial photos' fixed split (the training photos
    ``--aerial-repeats`` times), and the real negatives (training only)."""
    rendered = concat_datasets([(name, load_dataset(f, "sim")) for name, f in folders])
    classes = rendered.class_names
    train_ids, val_ids = split_ids(rendered.image_ids, train_cfg.val_fraction,
                                   train_cfg.split_seed)
    parts, val_parts = [("sim", rendered.subset(train_ids))], [("sim", rendered.subset(val_ids))]
    aerial_val = None
    if args.aerial is not None:
        aerial_train, aerial_val = aerial_split(args.aerial, classes)
        parts += [(f"aerial_{i}", aerial_train) for i in range(args.aerial_repeats)]
        val_parts.append(("aerial", aerial_val))
    if args.nadir:
        parts.append(("nadir", load_dataset(nadir_frames(args.cache, args.nadir), "yolo",
                                            classes)))
    if args.negatives is not None:
        parts.append(("negatives", load_dataset(args.negatives, None, classes)))
    return concat_datasets(parts), concat_datasets(val_parts), aerial_val


def micro_frames() -> list[Path]:
    """The real EuRoC frames of :data:`MICRO` (they show no target), or none when absent."""
    return sorted((MICRO / "mav0" / "cam0" / "data").glob("*.png"))


SOURCES_COMMAND = "python experiments/detect_sources.py --run RUN"


def _size_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _budget_callback(budget_s: float, t_start: float, curves):
    """``on_epoch``: draw the curves, then stop when another epoch like the last would end
    past the budget."""

    def on_epoch(history, det_cfg):
        curves(history, det_cfg)
        last = history[-1]
        epoch_s = last.get("train_time_s", 0.0) + last.get("eval_time_s", 0.0)
        if time.perf_counter() - t_start + epoch_s > budget_s:
            raise _BudgetSpent

    return on_epoch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--procedural", type=int, default=8, help="procedural flights")
    ap.add_argument("--steep", type=int, default=8,
                    help=f"procedural flights with the rig pitched {STEEP_PITCH_DEG:g} degrees")
    ap.add_argument("--euroc-flights", type=int, default=6,
                    help=f"EuRoC trajectories, the first of {EUROC_TRAIN}")
    ap.add_argument("--uzh-flights", type=int, default=4,
                    help=f"UZH-FPV indoor trajectories, the first of {UZH_TRAIN}")
    ap.add_argument("--aerial", type=_optional_dir, default=AERIAL,
                    help="real aerial photos, a YOLO folder ('none': rendered frames only) "
                         "[default: %(default)s]")
    ap.add_argument("--aerial-repeats", type=positive_int, default=AERIAL_REPEATS,
                    help="copies of each aerial training photo per epoch [default: %(default)s]")
    ap.add_argument("--negatives", type=_optional_dir, default=NEGATIVES,
                    help="real photos without targets, any labelled format ('none': no "
                         "negatives) [default: %(default)s]")
    ap.add_argument("--nadir", type=int, default=NADIR_FRAMES,
                    help="nadir street frames rendered (about 4 s each) [default: %(default)s]")
    ap.add_argument("--duration", type=positive, default=20.0, help="seconds per flight")
    ap.add_argument("--rate", type=positive, default=0.5, help="frames per second rendered")
    ap.add_argument("--low-res", action="store_true",
                    help="every flight also rendered at the fast size "
                         f"{LOW_RESOLUTION[0]}x{LOW_RESOLUTION[1]} (the demo's, the closed "
                         "loop's and the long flights'), upscaled at inference")
    ap.add_argument("--epochs", type=positive_int, default=SHIPPED.train.epochs,
                    help="[default: the preset's, %(default)s]")
    ap.add_argument("--budget", type=positive, default=40.0,
                    help="minutes of training at most [default: %(default)s]")
    ap.add_argument("--max-steps", type=positive_int, default=None,
                    help="batches per epoch at most (smoke runs)")
    ap.add_argument("--init", type=Path, default=None, metavar="RUN",
                    help="fine-tune RUN's weights (e.g. the shipped ones, the --out default) "
                         "instead of starting from random ones (train.init_from)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="DetectConfig fields (detector.*, train.*) over the preset")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "detector_cache",
                    help="rendered flights and the training run [default: %(default)s]")
    ap.add_argument("--out", type=Path, default=DEFAULT_DETECTOR_RUN,
                    help="where the shipped run goes [default: %(default)s]")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    add_write_docs(ap)
    args = ap.parse_args()
    t0 = time.perf_counter()
    enable_compilation_cache()
    show = not args.quiet

    items = flights(args)
    if not items:
        ap.error("no training flights")
    folders = [(name, cached_simulation(cfg, args.cache / "flights", name, progress=show))
               for name, cfg in progress_bar(items, desc="flights", enabled=show, unit="flight")]
    test_name, test_cfg = held_out()
    test_folder = cached_simulation(test_cfg, args.cache / "held_out", test_name, progress=show)
    t_sim = time.perf_counter() - t0

    # the preset, --epochs and --init, then --set
    config = apply_overrides(apply_overrides(SHIPPED, {
        "train.epochs": args.epochs,
        "train.init_from": None if args.init is None else str(args.init.absolute())}), args.set)
    dataset, val_set, aerial_val = training_sets(args, folders, config.train)
    run = args.cache / "run"
    shutil.rmtree(run, ignore_errors=True)
    t1 = time.perf_counter()
    stopped_early = False
    try:
        train(dataset, config.detector, config.train, run, val_dataset=val_set,
              progress=show,
              log=lambda line: print(line, file=sys.stderr, flush=True),
              max_steps_per_epoch=args.max_steps,
              on_epoch=_budget_callback(args.budget * 60.0, t1,
                                        training_curves_writer(RunPaths(run).png)))
    except _BudgetSpent:
        stopped_early = True
    t_train = time.perf_counter() - t1

    metrics = json.loads(RunPaths(run).json.read_text())
    best = next((r for r in metrics["history"] if r["epoch"] == metrics["best_epoch"]), {})
    # the parameters stored as float16 (half the size), and scored as they ship
    stage = export_run(run, args.cache / "export", params_dtype=PARAMS_DTYPE)
    sources = score_sources(stage, (test_name, test_cfg, test_folder), aerial_val,
                            micro_frames(), args.cache / "eval", SOURCES_COMMAND)
    target = export_run(stage, args.out, extra={"eval.json": sources})
    summary = {
        **{f"{source}_{key}": value for source, row in sources.items()
           for key, value in row.items() if key in ("map50", "map50_95", "per_frame")},
        "val_map50": best.get("map50"), "val_map50_95": best.get("map50_95"),
        "model": config.detector.model, "img_size": list(config.detector.img_size),
        "size_mb": round(_size_bytes(target) / 1e6, 3),
        "flights": len(folders), "images": len(dataset), "boxes": dataset.num_boxes,
        "epochs_run": len(metrics["history"]), "best_epoch": metrics["best_epoch"],
        "stopped_early": stopped_early,
        "simulate_s": round(t_sim, 1), "train_s": round(t_train, 1),
        "wall_s": round(time.perf_counter() - t0, 1), "out": str(target),
    }
    write_docs(args, "detector_default_weights", figures_table(summary),
               anchor=f"the held-out flight {test_name} and the real aerial photos' held-out "
                      "split, never trained on")
    print_json(summary)


if __name__ == "__main__":
    main()
