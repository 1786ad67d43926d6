"""``uavcal detect``: train, evaluate and run the target detector (YZNet-YOLO / YOLOv5n-like)."""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
from pathlib import Path

from uavcal_jax.argtypes import fraction, parse_imgsz, positive_int, print_json
from uavcal_jax.errors import DataError
from uavcal_jax.progress import progress

DESCRIPTION = """\
Train, evaluate and run the detector of RPEOD (YZNet backbone under a YOLOv5 v7.0 head;
RMSprop lr 0.01, momentum 0.9, weight decay 1e-5, batch 8, as the paper) or the YOLOv5n-like
baseline. Data sets are Pascal VOC folders (Annotations/ + JPEGImages/), YOLO folders (images
beside same-named .txt labels 'class cx cy w h' normalised, and classes.txt), COCO json files,
or a simulator output folder (mav0/target0). Corrupt images and malformed labels are skipped
with one warning listing them; images without labels are negatives."""

TRAIN_EPILOG = """\
The run folder RUN gets config.json (resolved configuration), split.json (the fixed 80/20
train/val split by image), metrics.csv/metrics.json (one row per epoch), curves.png,
checkpoints/last (resume with --resume) and checkpoints/best (EMA weights with the best
validation mAP@0.5:0.95), and export/detector.jax (the jax.export'ed predict function).

examples:
  uavcal detect train --data ../shared/data/detection/raccoon_voc --format voc --out runs/raccoon
  uavcal detect train --data DIR --out RUN --model yznet-yolo --epochs 300 --imgsz 640
  uavcal detect train --data DIR --out RUN --optimizer sgd --mosaic 1.0
  uavcal detect train --data DIR --out RUN --resume --epochs 400"""

EVAL_EPILOG = """\
Prints map50 (mAP@0.5) and map50_95 (mAP@0.5:0.95, COCO's 101-point interpolation, 100
detections per image; --voc07 for the 11-point VOC 2007 variant). Without --data the run's
own validation split is used.

examples:
  uavcal detect eval runs/raccoon
  uavcal detect eval runs/raccoon --data other_voc_folder --json"""

PREDICT_EPILOG = """\
Writes OUT/<image name> with the boxes drawn and OUT/detections.json, a COCO-format file
(images, categories, annotations with a score) that `uavcal detect eval` and COCO tools read.

examples:
  uavcal detect predict photos/ --checkpoint runs/raccoon --out out/pred
  uavcal detect predict 'frames/*.png' --checkpoint runs/raccoon --out out/pred --conf 0.4"""


def register(subparsers) -> None:
    from uavcal_jax.detect.config import MODELS
    from uavcal_jax.detect.datasets import FORMATS

    parser = subparsers.add_parser("detect", help="train, evaluate and run the target detector",
                                   description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="detect_command", metavar="ACTION", required=True)

    # ---------------------------------------------------------------- train
    p = sub.add_parser("train", help="train a detector on a VOC/YOLO/COCO/simulator data set",
                       description=DESCRIPTION, epilog=TRAIN_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, metavar="DIR", help="the data set folder (or COCO "
                   "json)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="data set format [default: detected from the folder]")
    p.add_argument("--out", required=True, metavar="RUN", help="the run folder to write")
    p.add_argument("--model", choices=MODELS, default="yznet-yolo-tiny",
                   help="detector [default: yznet-yolo-tiny]")
    p.add_argument("--epochs", type=positive_int, default=100, help="[default: 100]")
    p.add_argument("--imgsz", type=parse_imgsz, default=(480, 640), metavar="S|WxH",
                   help="network input, letterboxed: S for square, WxH otherwise (multiples "
                        "of 32) [default: 640x480, the paper's]")
    p.add_argument("--batch", type=positive_int, default=8, help="batch size [default: 8]")
    p.add_argument("--optimizer", choices=("rmsprop", "sgd"), default="rmsprop",
                   help="rmsprop: the paper (lr 0.01, momentum 0.9, weight decay 1e-5); sgd: "
                        "YOLOv5's (lr 0.01, Nesterov momentum 0.937, weight decay 5e-4, "
                        "warmup, linear decay) [default: rmsprop]")
    p.add_argument("--lr", type=float, default=None, help="initial learning rate "
                   "[default: 0.01]")
    p.add_argument("--schedule", choices=("constant", "linear", "cosine"), default=None,
                   help="learning-rate decay to lrf=0.01 [default: cosine for rmsprop, linear "
                        "for sgd]")
    p.add_argument("--warmup-epochs", type=float, default=3.0,
                   help="linear warmup (at least 100 steps, at most half the run) "
                        "[default: 3]")
    p.add_argument("--no-augment", action="store_true",
                   help="no augmentation (letterbox only)")
    p.add_argument("--mosaic", type=fraction, default=0.0,
                   help="probability of a 4-image mosaic [default: 0]")
    p.add_argument("--no-ema", action="store_true", help="evaluate/keep raw weights, no EMA")
    p.add_argument("--no-autoanchor", action="store_true",
                   help="keep the default anchors (default: YOLOv5's check against the "
                        "training labels, k-means anchors when best possible recall < 0.98)")
    p.add_argument("--val-data", metavar="DIR", default=None,
                   help="validate on this data set instead of the fixed split of --data")
    p.add_argument("--val-fraction", type=fraction, default=0.2,
                   help="fraction of images held out for validation [default: 0.2]")
    p.add_argument("--split-seed", type=int, default=0, help="seed of the split [default: 0]")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of initialisation, shuffling and augmentation [default: 0]")
    p.add_argument("--eval-every", type=positive_int, default=1,
                   help="validate every N epochs (and after the last) [default: 1]")
    p.add_argument("--select-metric", choices=("map50_95", "map50", "fitness"),
                   default="map50_95", help="best-model criterion [default: map50_95]")
    p.add_argument("--max-steps", type=positive_int, default=None, metavar="N",
                   help="cap batches per epoch (quick trials)")
    p.add_argument("--workers", type=positive_int, default=2,
                   help="data loading threads [default: 2]")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN from its last checkpoint (its saved configuration and "
                        "split; --epochs may be raised)")
    p.add_argument("--no-export", action="store_true",
                   help="do not write export/detector.jax at the end")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_train)

    # ---------------------------------------------------------------- eval
    p = sub.add_parser("eval", help="mAP@0.5 and mAP@0.5:0.95 of a trained run",
                       description="Evaluate a trained run (its best checkpoint).",
                       epilog=EVAL_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", metavar="RUN", help="a run folder written by `detect train`")
    p.add_argument("--data", metavar="DIR", default=None,
                   help="evaluate on all images of this data set [default: the run's "
                        "validation split]")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="format of --data [default: detected]")
    p.add_argument("--checkpoint", choices=("best", "last"), default="best",
                   help="which weights [default: best]")
    p.add_argument("--conf", type=float, default=0.001,
                   help="confidence threshold [default: 0.001, as YOLOv5 val]")
    p.add_argument("--iou", type=float, default=0.6, help="NMS IoU threshold [default: 0.6]")
    p.add_argument("--voc07", action="store_true", help="VOC 2007 11-point interpolation")
    p.add_argument("--batch", type=positive_int, default=8, help="[default: 8]")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_eval)

    # ---------------------------------------------------------------- predict
    p = sub.add_parser("predict", help="detect objects in images, draw boxes, write COCO json",
                       description="Run a trained detector on images.", epilog=PREDICT_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("images", nargs="+", metavar="IMAGES",
                   help="image files, folders (searched recursively) or glob patterns")
    p.add_argument("--checkpoint", required=True, metavar="RUN",
                   help="a run folder written by `detect train`")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--conf", type=float, default=0.25, help="[default: 0.25]")
    p.add_argument("--iou", type=float, default=0.45, help="NMS IoU threshold [default: 0.45]")
    p.add_argument("--max-det", type=positive_int, default=300, help="[default: 300]")
    p.add_argument("--batch", type=positive_int, default=1, help="[default: 1]")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_predict)


# ----------------------------------------------------------------------------- helpers


def _enable_compilation_cache() -> None:
    """Reuse XLA compilations across invocations (train -> eval -> predict compile the same
    functions). ``UAVCAL_JAX_CACHE`` chooses the folder; ``UAVCAL_JAX_CACHE=off`` disables."""
    import jax

    where = os.environ.get("UAVCAL_JAX_CACHE")
    if where == "off" or jax.config.jax_compilation_cache_dir:
        return  # disabled, or already set by the caller
    if where is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"),
                                                                  ".cache")
        where = os.path.join(base, "uavcal_jax", "xla")
    try:
        os.makedirs(where, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    except Exception:  # noqa: BLE001 - a cache is an optimisation only
        pass


def _log(enabled: bool):
    def log(line: str) -> None:
        if enabled:
            print(line, file=sys.stderr, flush=True)

    return log


def _progress(enabled: bool):
    def wrap(iterable, total=None, desc=""):
        return progress(iterable, total=total, desc=desc, enabled=enabled, unit="batch")

    return wrap


def _require_run(run: str) -> Path:
    path = Path(run)
    if not path.is_dir():
        raise DataError("no such run folder", path)
    if not (path / "config.json").is_file():
        raise DataError("not a training run (no config.json)", path)
    return path


# ----------------------------------------------------------------------------- train


def run_train(args) -> int:
    from uavcal_jax.detect.augment import AugmentConfig
    from uavcal_jax.detect.config import DetectorConfig
    from uavcal_jax.detect.datasets import load_dataset
    from uavcal_jax.detect.train import TrainConfig, train

    data = Path(args.data)
    if not data.exists():
        raise DataError("no such data folder", data)
    _enable_compilation_cache()
    t0 = time.perf_counter()
    dataset = load_dataset(data, args.format)
    if not len(dataset):
        raise DataError("no usable images", data)
    val = load_dataset(args.val_data, args.format, dataset.class_names) \
        if args.val_data else None
    common = dict(epochs=args.epochs, batch_size=args.batch, warmup_epochs=args.warmup_epochs,
                  augment=None if args.no_augment else AugmentConfig(mosaic=args.mosaic),
                  ema=not args.no_ema, val_fraction=args.val_fraction,
                  split_seed=args.split_seed, seed=args.seed, eval_every=args.eval_every,
                  select_metric=args.select_metric, workers=args.workers,
                  autoanchor=not args.no_autoanchor)
    if args.lr is not None:
        common["lr"] = args.lr
    if args.schedule is not None:
        common["lr_schedule"] = args.schedule
    cfg = TrainConfig.yolov5(**common) if args.optimizer == "sgd" else TrainConfig.paper(
        **common)
    det_cfg = DetectorConfig(model=args.model, num_classes=max(1, dataset.num_classes),
                             img_size=args.imgsz)
    show = not args.json
    summary = train(dataset, det_cfg, cfg, args.out, resume=args.resume, val_dataset=val,
                    progress=_progress(show), log=_log(show),
                    max_steps_per_epoch=args.max_steps)
    if not args.no_export:
        from uavcal_jax.detect.export import export_predict
        from uavcal_jax.detect.train import load_run

        loaded = load_run(args.out)
        path = export_predict(loaded.variables, loaded.det_cfg,
                              Path(args.out) / "export" / "detector.jax",
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
    from uavcal_jax.detect.datasets import load_dataset
    from uavcal_jax.detect.loader import DetectionLoader
    from uavcal_jax.detect.train import (
        evaluate_predictions,
        load_run,
        make_predict,
        predict_dataset,
    )

    run = _require_run(args.run)
    if args.data is not None and not Path(args.data).exists():
        raise DataError("no such data folder", args.data)
    _enable_compilation_cache()
    t0 = time.perf_counter()
    loaded = load_run(run, args.checkpoint)
    class_names = loaded.data["class_names"]
    if args.data is not None:
        dataset = load_dataset(args.data, args.format, class_names)
        where = str(args.data)
    else:
        root = loaded.data["root"]
        if not Path(root).exists():
            raise DataError("the run's data set is gone; pass --data", root)
        dataset = load_dataset(root, loaded.data["format"], class_names)
        val_ids = (loaded.split or {}).get("val") or []
        if val_ids:
            dataset = dataset.subset(val_ids)
        where = f"{root} (validation split, {len(val_ids)} images)" if val_ids else root
    if not len(dataset):
        raise DataError("no images to evaluate", args.data or loaded.data["root"])
    det_cfg = loaded.det_cfg
    loader = DetectionLoader(dataset, det_cfg.img_size, args.batch, include_difficult=True,
                             cache=False)
    predict_fn = make_predict(det_cfg, args.conf, args.iou, loaded.train_cfg.max_det)
    dets = predict_dataset(predict_fn, loaded.variables, loader,
                           progress=_progress(not args.json))
    loader.close()
    result = evaluate_predictions(dataset.records, dets, det_cfg.num_classes,
                                  loaded.train_cfg.map_max_dets,
                                  "voc07" if args.voc07 else "coco101")
    out = result.as_dict(class_names)
    out.update(run=str(run), data=where, num_images=len(dataset),
               num_boxes=int(sum(len(r) for r in dataset.records)),
               interpolation="voc07" if args.voc07 else "coco101",
               checkpoint_epoch=loaded.meta.get("epoch", -1) + 1,
               wall_s=round(time.perf_counter() - t0, 2))
    (run / "eval.json").write_text(json.dumps(out, indent=1))
    if args.json:
        print_json(out)
    else:
        print(f"{run}: {len(dataset)} images of {where}")
        print(f"map50 {out['map50']:.4f}")
        print(f"map50_95 {out['map50_95']:.4f}")
        for name, pc in out["per_class"].items():
            if pc["num_gt"]:
                print(f"  {name}: ap50 {pc['ap50']:.4f}  ap50_95 {pc['ap50_95']:.4f}  "
                      f"({pc['num_gt']} boxes)")
    return 0


# ----------------------------------------------------------------------------- predict


def collect_images(items) -> list[Path]:
    """Files, folders (recursive) and glob patterns -> a sorted list of image paths."""
    from uavcal_jax.detect.datasets import IMAGE_SUFFIXES

    found: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found += [p for p in sorted(path.rglob("*")) if p.suffix.lower() in IMAGE_SUFFIXES]
        elif path.is_file():
            found.append(path)
        elif any(c in item for c in "*?["):
            found += [Path(p) for p in sorted(glob.glob(item, recursive=True))
                      if Path(p).suffix.lower() in IMAGE_SUFFIXES]
        else:
            raise DataError("no such image file or folder", path)
    unique = list(dict.fromkeys(p.resolve() for p in found))
    if not unique:
        raise DataError("no images found", " ".join(items))
    return unique


def draw_detections(image_bgr, boxes, scores, classes, class_names):
    """Boxes with "name score" labels drawn on a copy of a BGR image."""
    import cv2
    import numpy as np

    out = image_bgr.copy()
    thick = max(1, round(sum(out.shape[:2]) / 600))
    for (x0, y0, x1, y1), s, c in zip(boxes, scores, classes, strict=True):
        hue = (int(c) * 47) % 180
        color = tuple(int(v) for v in cv2.cvtColor(
            np.uint8([[[hue, 220, 255]]]), cv2.COLOR_HSV2BGR)[0, 0])
        p0, p1 = (int(round(x0)), int(round(y0))), (int(round(x1)), int(round(y1)))
        cv2.rectangle(out, p0, p1, color, thick)
        name = class_names[int(c)] if int(c) < len(class_names) else str(int(c))
        label = f"{name} {float(s):.2f}"
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thick, 1)
        top = max(p0[1] - th - 4, 0)
        cv2.rectangle(out, (p0[0], top), (p0[0] + tw + 2, top + th + 4), color, -1)
        cv2.putText(out, label, (p0[0] + 1, top + th + 1), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * thick, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def run_predict(args) -> int:
    import cv2
    import jax.numpy as jnp
    import numpy as np

    from uavcal_jax.detect.augment import letterbox, unletterbox_boxes
    from uavcal_jax.detect.datasets import IMREAD_FLAGS
    from uavcal_jax.detect.train import load_run, make_predict
    from uavcal_jax.errors import DataRepairWarning

    run = _require_run(args.checkpoint)
    paths = collect_images(args.images)
    _enable_compilation_cache()
    t0 = time.perf_counter()
    loaded = load_run(run)
    det_cfg = loaded.det_cfg
    class_names = loaded.data["class_names"]
    category_ids = loaded.data.get("category_ids") or list(range(len(class_names)))
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    predict_fn = make_predict(det_cfg, args.conf, args.iou, args.max_det, multi_label=False)
    H, W = det_cfg.img_size
    common_root = Path(os.path.commonpath([str(p.parent) for p in paths]))
    images_doc, anns, unreadable = [], [], []
    n_det = 0
    bar = progress(total=len(paths), desc="predict", enabled=not args.json, unit="img")
    for start in range(0, len(paths), args.batch):
        chunk = paths[start:start + args.batch]
        originals, batch, metas = [], np.full((args.batch, H, W, 3), 114 / 255, np.float32), []
        for path in chunk:
            img = cv2.imread(str(path), IMREAD_FLAGS)
            if img is None:
                unreadable.append(str(path))
                continue
            boxed, ratio, pad = letterbox(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), (H, W))
            batch[len(originals)] = boxed.astype(np.float32) / 255.0
            originals.append((path, img))
            metas.append((ratio, pad))
        if originals:
            det = predict_fn(loaded.variables, jnp.asarray(batch))
            boxes, scores = np.asarray(det.boxes), np.asarray(det.scores)
            classes, valid = np.asarray(det.classes), np.asarray(det.valid)
        for j, ((path, img), (ratio, pad)) in enumerate(zip(originals, metas, strict=True)):
            keep = valid[j].astype(bool)
            h, w = img.shape[:2]
            b = unletterbox_boxes(boxes[j][keep], ratio, pad, (w, h))
            s, c = scores[j][keep], classes[j][keep]
            rel = path.relative_to(common_root)
            target = out_dir / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(target), draw_detections(img, b, s, c, class_names))
            image_id = len(images_doc) + 1
            images_doc.append({"id": image_id, "file_name": rel.as_posix(), "width": w,
                               "height": h, "path": str(path)})
            for box, score, cls in zip(b, s, c, strict=True):
                bw, bh = float(box[2] - box[0]), float(box[3] - box[1])
                anns.append({"id": len(anns) + 1, "image_id": image_id,
                             "category_id": int(category_ids[int(cls)]),
                             "bbox": [round(float(box[0]), 2), round(float(box[1]), 2),
                                      round(bw, 2), round(bh, 2)],
                             "area": round(bw * bh, 2), "score": round(float(score), 5),
                             "iscrowd": 0})
            n_det += len(b)
        bar.update(len(chunk))
    bar.close()
    if unreadable:
        import warnings

        warnings.warn(f"skipped {len(unreadable)} unreadable images: "
                      f"{', '.join(unreadable[:20])}", DataRepairWarning, stacklevel=1)
    if not images_doc:
        raise DataError("none of the images could be read", args.images[0])
    doc = {"info": {"description": f"uavcal detect predict ({det_cfg.model})",
                    "run": str(run), "conf_thresh": args.conf, "iou_thresh": args.iou},
           "images": images_doc,
           "categories": [{"id": int(i), "name": n} for i, n in zip(category_ids, class_names,
                                                                     strict=True)],
           "annotations": anns}
    (out_dir / "detections.json").write_text(json.dumps(doc))
    summary = {"out": str(out_dir), "images": len(images_doc), "detections": n_det,
               "skipped": unreadable, "json": str(out_dir / "detections.json"),
               "wall_s": round(time.perf_counter() - t0, 2)}
    if args.json:
        print_json(summary)
    else:
        print(f"{n_det} detections in {len(images_doc)} images -> {out_dir}")
    return 0

