"""Evaluate a trained run: the mAP of its checkpoint on its validation split or another set."""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path

from uavcal_jax.data.detection_records import DetectionDataset
from uavcal_jax.detect.datasets import load_dataset, remap_classes
from uavcal_jax.detect.loader import DetectionLoader, read_image_rgb
from uavcal_jax.detect.metrics import evaluate_predictions
from uavcal_jax.detect.predict import make_predict_fn, predict_dataset
from uavcal_jax.detect.run import load_run
from uavcal_jax.detect.tile import TileConfig, detect_tiled, needs_slicing
from uavcal_jax.errors import DataError
from uavcal_jax.runs import results_folder

#: The scores an evaluation writes into its results folder.
EVAL_FILE = "eval.json"


def evaluate_run(run: str | Path, data: str | Path | DetectionDataset | None = None,
                 data_format: str | None = None,
                 *, which: str = "best", batch_size: int | None = None,
                 interpolation: str = "coco101", progress: Callable | None = None,
                 out_dir: str | Path | None = None, tile: TileConfig | None = None,
                 **predict_changes) -> dict:
    """mAP@0.5 and mAP@0.5:0.95 of a run's checkpoint; also written to ``eval.json`` in
    ``out_dir`` (default :func:`uavcal_jax.runs.results_folder` of ``run``: the run folder,
    or ``./uavcal_eval/<run name>`` for the shipped weights; never into the package).

    Args:
        run: a run folder written by :func:`~uavcal_jax.detect.train.train`.
        data: evaluate on every image of this data set (a folder read with ``data_format``,
            or a loaded :class:`DetectionDataset`, e.g. a split's subset; in the run's class
            list); by default the run's own validation split of its training data.
        which: ``"best"`` or ``"last"`` checkpoint.
        batch_size: default the run's training batch size.
        interpolation: ``"coco101"`` or ``"voc07"``.
        progress: ``progress(iterable, total=...)`` wrapper of the batches (of the images
            with ``tile``).
        tile: sliced inference (:func:`uavcal_jax.detect.tile.detect_tiled`) of the images
            it slices (:func:`~uavcal_jax.detect.tile.needs_slicing`), one at a time, their
            windows in batches of ``tile.batch_size``; ``None`` for none.
        predict_changes: :class:`~uavcal_jax.detect.config.PredictConfig` fields replaced in
            the run's ``TrainConfig.predict`` (e.g. ``conf_thresh``).

    Returns :meth:`~uavcal_jax.detect.metrics.MapResult.as_dict` plus where the images came
    from, their number and boxes, the checkpoint's epoch and the wall time, and ``out``: the
    ``eval.json`` written.
    """
    t0 = time.perf_counter()
    run = Path(run)
    loaded = load_run(run, which)
    class_names = loaded.data["class_names"]
    if isinstance(data, DetectionDataset):
        dataset = remap_classes(data, class_names)
        where = f"{data.root} ({len(data)} images)"
    elif data is not None:
        dataset = load_dataset(data, data_format, class_names)
        where = str(data)
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
        raise DataError("no images to evaluate", data or loaded.data["root"])
    det_cfg, train_cfg = loaded.det_cfg, loaded.train_cfg
    predict_cfg = train_cfg.predict.replace(**predict_changes)
    predict_fn = functools.partial(make_predict_fn(det_cfg, predict_cfg), loaded.variables)
    # images the tiling slices one at a time, the rest letterboxed whole in batches
    sliced = [needs_slicing((r.height, r.width), det_cfg.img_size, tile)
              for r in dataset.records]
    whole = [r for r, s in zip(dataset.records, sliced, strict=True) if not s]
    whole_dets = iter(())
    if whole:
        loader = DetectionLoader(whole, det_cfg.img_size, batch_size or train_cfg.batch_size,
                                 include_difficult=True, cache=False)
        try:
            whole_dets = iter(predict_dataset(predict_fn, loader, progress=progress))
        finally:
            loader.close()
    cut = [r for r, s in zip(dataset.records, sliced, strict=True) if s]
    cut_dets = iter([detect_tiled(predict_fn, [read_image_rgb(r.image_path)],
                                  det_cfg.img_size, tile, predict_cfg.max_det)[0]
                     for r in (cut if progress is None or not cut
                               else progress(cut, total=len(cut)))])
    dets = [next(cut_dets) if s else next(whole_dets) for s in sliced]
    result = evaluate_predictions(dataset.records, dets, det_cfg.num_classes,
                                  train_cfg.map_max_dets, interpolation)
    out = result.as_dict(class_names)
    out.update(run=str(run), data=where, num_images=len(dataset), num_boxes=dataset.num_boxes,
               interpolation=interpolation, checkpoint_epoch=loaded.meta["epoch"],
               wall_s=round(time.perf_counter() - t0, 2))
    if tile is not None:
        out["tile"] = dataclasses.asdict(tile)
        out["sliced_images"] = sum(sliced)
    folder = results_folder(run, out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / EVAL_FILE).write_text(json.dumps(out, indent=1))
    return {**out, "out": str(folder / EVAL_FILE)}
