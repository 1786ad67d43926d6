"""``uavcal detect``: train, evaluate and run the target detector (YZNet-YOLO / YOLOv5n-like).

Every option's default and choices come from the configuration dataclasses and constants of
:mod:`uavcal_jax.detect.config` (and :mod:`~uavcal_jax.data.detection_labels`,
:mod:`~uavcal_jax.detect.run`); the help texts print them from there.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
import time
from pathlib import Path

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.config import apply_overrides, valid_keys, write_config
from uavcal_jax.errors import DataError
from uavcal_jax.progress import progress
from uavcal_jax.xla_cache import enable_compilation_cache

DESCRIPTION = """\
Train, evaluate and run the detector of RPEOD (YZNet backbone under a YOLOv5 v7.0 head;
RMSprop lr {p.lr:g}, momentum {p.momentum:g}, weight decay {p.weight_decay:g}, batch {p.batch_size},
as the paper) or the YOLOv5n-like baseline. Data sets are Pascal VOC folders (Annotations/ +
JPEGImages/), YOLO folders (images beside same-named .txt labels 'class cx cy w h' normalised,
and classes.txt), COCO json files, or a simulator output folder (mav0/target0). Corrupt images
and malformed labels are skipped with one warning listing them; images without labels are
negatives."""

TRAIN_EPILOG = """\
The run folder RUN gets config.json (the resolved configuration: the options, then any --set),
split.json (the fixed train/val split by image), metrics.csv/metrics.json (one row per epoch),
curves.png, checkpoints/last (resume with --resume) and checkpoints/best (EMA weights with the
best validation mAP@0.5:0.95), and export/detector.jax (the jax.export'ed predict function).

examples:
  uavcal detect train --data ../shared/data/detection/raccoon_voc --format voc --out runs/raccoon
  uavcal detect train --data DIR --out RUN --model yznet-yolo --epochs 300 --imgsz 640
  uavcal detect train --data DIR --out RUN --optimizer sgd --mosaic 1.0
  uavcal detect train --data DIR --out RUN --resume --epochs 400
  uavcal detect train --data DIR --out RUN --set train.augment.scale=0.3 detector.anchor_t=3

--set keys:
{keys}"""

EVAL_EPILOG = """\
Prints map50 (mAP@0.5) and map50_95 (mAP@0.5:0.95, COCO's 101-point interpolation, {n}
detections per image; --voc07 for the 11-point VOC 2007 variant). Without --data the run's
own validation split is used. Writes eval.json (the scores) and eval_config.json (the
resolved prediction settings: the run's, --conf and --iou, then any --set; --tile's) into
--out; without --out into RUN, or, when RUN is inside the installed package (the shipped
weights) or not writable, into ./{home}/<RUN's name> (said on stderr): never into the
package.

examples:
  uavcal detect eval runs/raccoon
  uavcal detect eval runs/raccoon --data other_voc_folder --json
  uavcal detect eval runs/raccoon --set multi_label=false
  uavcal detect eval {shipped} --data my_yolo_folder --format yolo --out eval/mine

--set keys (prediction settings):
{keys}"""

PREDICT_EPILOG = """\
Writes OUT/<image name> with the boxes drawn, OUT/detections.json, a COCO-format file
(images, categories, annotations with a score) that `uavcal detect eval` and COCO tools read,
and OUT/predict_config.json (the resolved prediction settings: the options, then any --set).

examples:
  uavcal detect predict photos/ --checkpoint runs/raccoon --out out/pred
  uavcal detect predict 'frames/*.png' --checkpoint runs/raccoon --out out/pred --conf 0.4
  uavcal detect predict photos/ --checkpoint runs/raccoon --out out/pred --set agnostic=true
  uavcal detect predict aerial/ --checkpoint runs/raccoon --out out/pred --tile

--set keys (prediction settings):
{keys}"""

#: Images per call of `detect predict` (serving one image at a time by default).
PREDICT_BATCH = 1
#: Beside the results of `detect eval` and `detect predict` (in their --out): the resolved
#: :class:`~uavcal_jax.detect.config.PredictConfig`.
EVAL_CONFIG, PREDICT_CONFIG = "eval_config.json", "predict_config.json"


def _keys(config_cls) -> str:
    """The ``--set`` keys of ``config_cls``, wrapped for an epilog."""
    return textwrap.fill(", ".join(valid_keys(config_cls)), 88, initial_indent="  ",
                         subsequent_indent="  ")


def _add_set(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                        help=f"set {what} (keys below), applied after the options; "
                             "repeatable; an unknown key is an error naming it")


def register(subparsers) -> None:
    from uavcal_jax.data.detection_labels import LABEL_FORMATS
    from uavcal_jax.detect.config import (
        EVAL_PREDICT,
        SERVE_PREDICT,
        DetectConfig,
        PredictConfig,
        TrainConfig,
    )
    from uavcal_jax.detect.options import add_train_options
    from uavcal_jax.runs import EVAL_HOME, KINDS

    description = DESCRIPTION.format(p=TrainConfig.paper())
    raw = argparse.RawDescriptionHelpFormatter
    parser = subparsers.add_parser("detect", help="train, evaluate and run the target detector",
                                   description=description, formatter_class=raw)
    sub = parser.add_subparsers(dest="detect_command", metavar="ACTION", required=True)

    # ---------------------------------------------------------------- train
    p = sub.add_parser("train", help="train a detector on a VOC/YOLO/COCO/simulator data set",
                       description=description,
                       epilog=TRAIN_EPILOG.format(keys=_keys(DetectConfig)), formatter_class=raw)
    p.add_argument("--data", required=True, metavar="DIR", help="the data set folder (or COCO "
                   "json)")
    p.add_argument("--format", choices=LABEL_FORMATS, default=None,
                   help="data set format [default: detected from the folder]")
    p.add_argument("--out", required=True, metavar="RUN", help="the run folder to write")
    add_train_options(p)
    p.add_argument("--val-data", metavar="DIR", default=None,
                   help="validate on this data set instead of the fixed split of --data")
    p.add_argument("--max-steps", type=positive_int, default=None, metavar="N",
                   help="cap batches per epoch (quick trials)")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN from its last checkpoint (its saved configuration and "
                        "split; --epochs may be raised)")
    p.add_argument("--no-export", action="store_true",
                   help="do not write export/detector.jax at the end")
    _add_set(p, "detector and training fields")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_train)

    # ---------------------------------------------------------------- eval
    p = sub.add_parser("eval", help="mAP@0.5 and mAP@0.5:0.95 of a trained run",
                       description="Evaluate a trained run (its best checkpoint).",
                       epilog=EVAL_EPILOG.format(n=TrainConfig.map_max_dets,
                                                 keys=_keys(PredictConfig), home=EVAL_HOME,
                                                 shipped=_shipped()),
                       formatter_class=raw)
    p.add_argument("run", metavar="RUN", help="a run folder written by `detect train`")
    p.add_argument("--data", metavar="DIR", default=None,
                   help="evaluate on all images of this data set [default: the run's "
                        "validation split]")
    p.add_argument("--format", choices=LABEL_FORMATS, default=None,
                   help="format of --data [default: detected]")
    p.add_argument("--checkpoint", choices=KINDS, default=KINDS[0],
                   help="which weights [default: %(default)s]")
    p.add_argument("--conf", type=float, default=EVAL_PREDICT.conf_thresh,
                   help="confidence threshold [default: %(default)s, as YOLOv5 val]")
    p.add_argument("--iou", type=float, default=EVAL_PREDICT.iou_thresh,
                   help="NMS IoU threshold [default: %(default)s]")
    p.add_argument("--voc07", action="store_true", help="VOC 2007 11-point interpolation")
    p.add_argument("--out", metavar="DIR", default=None,
                   help=f"write eval.json and eval_config.json here [default: RUN; ./{EVAL_HOME}/"
                        "<RUN's name> when RUN is the shipped weights or not writable]")
    _add_tile(p)
    _add_set(p, "prediction settings")
    p.add_argument("--batch", type=positive_int, default=TrainConfig.batch_size,
                   help="[default: %(default)s]")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_eval)

    # ---------------------------------------------------------------- predict
    p = sub.add_parser("predict", help="detect objects in images, draw boxes, write COCO json",
                       description="Run a trained detector on images.",
                       epilog=PREDICT_EPILOG.format(keys=_keys(PredictConfig)),
                       formatter_class=raw)
    p.add_argument("images", nargs="+", metavar="IMAGES",
                   help="image files, folders (searched recursively) or glob patterns")
    p.add_argument("--checkpoint", required=True, metavar="RUN",
                   help="a run folder written by `detect train`")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--conf", type=float, default=SERVE_PREDICT.conf_thresh,
                   help="[default: %(default)s]")
    p.add_argument("--iou", type=float, default=SERVE_PREDICT.iou_thresh,
                   help="NMS IoU threshold [default: %(default)s]")
    p.add_argument("--max-det", type=positive_int, default=SERVE_PREDICT.max_det,
                   help="[default: %(default)s]")
    p.add_argument("--batch", type=positive_int, default=PREDICT_BATCH,
                   help="[default: %(default)s]")
    _add_tile(p)
    _add_set(p, "prediction settings")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_predict)


# ----------------------------------------------------------------------------- helpers


def _log(enabled: bool):
    def log(line: str) -> None:
        if enabled:
            print(line, file=sys.stderr, flush=True)

    return log


def _progress(enabled: bool):
    def wrap(iterable, total=None, desc=""):
        return progress(iterable, total=total, desc=desc, enabled=enabled, unit="batch")

    return wrap


def _shipped() -> str:
    """The shipped detector weights' folder, as a user types it in an example."""
    from uavcal_jax.detect.default_weights import DEFAULT_DETECTOR_RUN

    return str(DEFAULT_DETECTOR_RUN)


def _redirect_note(run: Path, out: str | None, folder: Path) -> None:
    """Say on stderr when an evaluation of ``run`` went elsewhere than ``run`` without --out
    (:func:`uavcal_jax.runs.results_redirect`)."""
    from uavcal_jax.runs import results_redirect

    why = results_redirect(run) if out is None else None
    if why is not None:
        print(f"{run} {why}: the evaluation went to {folder} (--out DIR chooses)",
              file=sys.stderr, flush=True)


def _add_tile(parser: argparse.ArgumentParser) -> None:
    from uavcal_jax.detect.tile import AUTO_MIN_SCALE, TILE_MODES, TileConfig

    parser.add_argument("--tile", nargs="?", choices=TILE_MODES, default="auto", const="on",
                        metavar="{" + ",".join(TILE_MODES) + "}",
                        help="sliced inference (SAHI): run the network on overlapping windows "
                             "of each image at its own resolution, each of the network "
                             "input's size, and on the whole image, and merge the boxes "
                             "(class-wise NMS, intersection over the smaller box > "
                             f"{TileConfig.match_thresh:g}): small objects in large images. "
                             f"auto: slice images over {AUTO_MIN_SCALE:g} times the input's "
                             "width or height, letterbox the rest whole; on (--tile alone): "
                             "slice every image larger than the input; off: none. Windows go "
                             f"{TileConfig.batch_size} to a network call, one image at a time "
                             "(--batch is for whole images) [default: %(default)s]")
    parser.add_argument("--tile-overlap", type=float, default=TileConfig.overlap, metavar="R",
                        help="the least overlap of neighbouring windows, a fraction of a "
                             "window's side [default: %(default)s]")


def _tile(args):
    """The :class:`~uavcal_jax.detect.tile.TileConfig` of ``--tile`` (``None`` for ``off``);
    a bad ``--tile-overlap`` is a DataError."""
    from uavcal_jax.detect.tile import TileConfig

    try:
        return TileConfig.of_mode(args.tile, overlap=args.tile_overlap)
    except ValueError as err:
        raise DataError(f"--tile-overlap: {err}") from None


def _tile_extra(tile) -> dict:
    """The ``tile`` entry of a written prediction config (none without tiling: the file is
    what it was before tiling existed)."""
    import dataclasses

    return {} if tile is None else {"tile": dataclasses.asdict(tile)}


def _require_run(run: str) -> Path:
    path = Path(run)
    if not path.is_dir():
        raise DataError("no such run folder", path)
    if not (path / "config.json").is_file():
        raise DataError("not a training run (no config.json)", path)
    return path


# ----------------------------------------------------------------------------- train


def run_train(args) -> int:
    from uavcal_jax.detect.datasets import load_dataset
    from uavcal_jax.detect.options import train_options
    from uavcal_jax.detect.run import RunPaths
    from uavcal_jax.detect.train import train
    from uavcal_jax.plots import training_curves_writer

    # the options, then --set (num_classes comes from the data set)
    config = apply_overrides(train_options(args), args.set)
    data = Path(args.data)
    if not data.exists():
        raise DataError("no such data folder", data)
    enable_compilation_cache()
    t0 = time.perf_counter()
    dataset = load_dataset(data, args.format)
    if not len(dataset):
        raise DataError("no usable images", data)
    val = load_dataset(args.val_data, args.format, dataset.class_names) \
        if args.val_data else None
    det_cfg = config.detector.replace(num_classes=max(1, dataset.num_classes))
    show = not args.json
    summary = train(dataset, det_cfg, config.train, args.out, resume=args.resume,
                    val_dataset=val, progress=show, log=_log(show),
                    max_steps_per_epoch=args.max_steps,
                    on_epoch=training_curves_writer(RunPaths(Path(args.out)).png))
    if not args.no_export:
        from uavcal_jax.detect.export import export_predict
        from uavcal_jax.detect.run import load_run

        loaded = load_run(args.out)
        path = export_predict(loaded.variables, loaded.det_cfg, RunPaths(Path(args.out)).export,
                              class_names=loaded.data["class_names"])
        summary["export"] = str(path)
    summary.update(data=str(data), format=dataset.format, classes=list(dataset.class_names),
                   wall_s=round(time.perf_counter() - t0, 2))
    if args.json:
        print_json(summary)
    else:
        print(f"trained {summary['model']} for {summary['epochs']} epochs -> {args.out}")
        if summary.get("map50") is not None:
            print(f"best epoch {summary['best_epoch']}: map50 {summary['map50']:.4f}  "
                  f"map50_95 {summary['map50_95']:.4f}")
    return 0


# ----------------------------------------------------------------------------- eval


def run_eval(args) -> int:
    import dataclasses

    from uavcal_jax.detect.evaluate import evaluate_run
    from uavcal_jax.detect.run import RunPaths, read_config
    from uavcal_jax.runs import results_folder

    run = _require_run(args.run)
    # the run's validation settings, --conf and --iou, then --set
    predict_cfg = apply_overrides(read_config(RunPaths(run))[0].train.predict.replace(
        conf_thresh=args.conf, iou_thresh=args.iou), args.set)
    if args.data is not None and not Path(args.data).exists():
        raise DataError("no such data folder", args.data)
    tile = _tile(args)
    enable_compilation_cache()
    interpolation = "voc07" if args.voc07 else "coco101"
    folder = results_folder(run, args.out)
    out = evaluate_run(run, args.data, args.format, which=args.checkpoint,
                       batch_size=args.batch, interpolation=interpolation,
                       progress=_progress(not args.json), out_dir=folder, tile=tile,
                       **dataclasses.asdict(predict_cfg))
    out["config"] = str(write_config(folder / EVAL_CONFIG, predict_cfg,
                                     checkpoint=args.checkpoint, data=args.data,
                                     format=args.format, batch=args.batch,
                                     interpolation=interpolation, **_tile_extra(tile)))
    _redirect_note(run, args.out, folder)
    if args.json:
        print_json(out)
    else:
        print(f"{run}: {out['num_images']} images of {out['data']}")
        print(f"map50 {out['map50']:.4f}")
        print(f"map50_95 {out['map50_95']:.4f}")
        for name, pc in out["per_class"].items():
            if pc["num_gt"]:
                print(f"  {name}: ap50 {pc['ap50']:.4f}  ap50_95 {pc['ap50_95']:.4f}  "
                      f"({pc['num_gt']} boxes)")
    return 0


# ----------------------------------------------------------------------------- predict


def run_predict(args) -> int:
    import functools

    from uavcal_jax.data.detection_records import collect_images
    from uavcal_jax.detect.annotate import annotate_files
    from uavcal_jax.detect.config import SERVE_PREDICT
    from uavcal_jax.detect.predict import make_predict_fn
    from uavcal_jax.detect.run import load_run

    run = _require_run(args.checkpoint)
    # the options, then --set
    predict_cfg = apply_overrides(SERVE_PREDICT.replace(
        conf_thresh=args.conf, iou_thresh=args.iou, max_det=args.max_det), args.set)
    tile = _tile(args)
    paths = collect_images(args.images)
    enable_compilation_cache()
    t0 = time.perf_counter()
    loaded = load_run(run)
    predict_fn = functools.partial(make_predict_fn(loaded.det_cfg, predict_cfg),
                                   loaded.variables)
    summary = annotate_files(
        predict_fn, paths, loaded.det_cfg.img_size, args.out, loaded.data["class_names"],
        category_ids=loaded.data.get("category_ids") or None, batch_size=args.batch,
        info={"description": f"uavcal detect predict ({loaded.det_cfg.model})",
              "run": str(run), "conf_thresh": predict_cfg.conf_thresh,
              "iou_thresh": predict_cfg.iou_thresh, **_tile_extra(tile)},
        progress=lambda total: progress(total=total, desc="predict", enabled=not args.json,
                                        unit="img"),
        tile=tile, max_det=predict_cfg.max_det)
    summary["config"] = str(write_config(Path(args.out) / PREDICT_CONFIG, predict_cfg,
                                         checkpoint=str(run), batch=args.batch,
                                         **_tile_extra(tile)))
    summary["wall_s"] = round(time.perf_counter() - t0, 2)
    if args.json:
        print_json(summary)
    else:
        print(f"{summary['detections']} detections in {summary['images']} images -> "
              f"{summary['out']}")
    return 0
