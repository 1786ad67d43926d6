"""Training the detector: the loop around the pure step, with checkpoints, resume and
best-model selection on validation mAP.

The numerics live elsewhere and are pure: the optimiser in :mod:`.optim`, the jitted step and
its EMA in :mod:`.step`, prediction in :mod:`.predict`, the mAP in :mod:`.metrics`. This module
has the side effects: data loading, checkpoints, the run folder (:mod:`.run`) and progress.

Best model: after each evaluation the EMA weights are scored on the validation split by
``TrainConfig.select_metric`` (default ``map50_95``; ``map50`` or YOLOv5's
``fitness = 0.1 map50 + 0.9 map50_95``) and the best are saved to ``checkpoints/best``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from uavcal_jax.data.detection_records import DetectionDataset
from uavcal_jax.detect.anchors import check_anchors, label_sizes
from uavcal_jax.detect.checkpoint import Checkpoints
from uavcal_jax.detect.config import DetectorConfig, TrainConfig
from uavcal_jax.detect.datasets import load_dataset, save_split, split_ids
from uavcal_jax.detect.loader import DetectionLoader
from uavcal_jax.detect.metrics import evaluate_predictions, fitness
from uavcal_jax.detect.optim import current_lr
from uavcal_jax.detect.predict import make_predict_fn, predict_dataset
from uavcal_jax.detect.run import (
    RunPaths,
    read_config,
    read_split,
    write_config,
    write_metrics,
)
from uavcal_jax.detect.step import compiled_training, init_train_state
from uavcal_jax.errors import DataError


def prepare_split(dataset: DetectionDataset, cfg: TrainConfig, val_dataset=None):
    """``(train, val)`` data sets: ``val_dataset`` if given, else the fixed split."""
    if val_dataset is not None:
        return dataset, val_dataset
    if cfg.val_fraction <= 0:
        return dataset, None
    train_ids, val_ids = split_ids(dataset.image_ids, cfg.val_fraction, cfg.split_seed)
    return dataset.subset(train_ids), dataset.subset(val_ids)


def _resolve(paths: RunPaths, dataset: DetectionDataset, det_cfg: DetectorConfig,
             cfg: TrainConfig, resume: bool, val_dataset, log):
    """The configurations and the (train, val) sets of this call: the saved ones when
    resuming (``cfg.epochs`` may be raised), else fresh ones with autoanchor."""
    if not resume:
        train_set, val_set = prepare_split(dataset, cfg, val_dataset)
        wh = label_sizes(train_set, det_cfg.img_size)
        if cfg.autoanchor and len(wh):  # YOLOv5's train.py: fit anchors to the labels
            det_cfg, report = check_anchors(det_cfg, wh, seed=cfg.seed)
            if log is not None:
                log(json.dumps({"autoanchor": report}))
        return det_cfg, cfg, train_set, val_set
    if not paths.config.is_file():
        raise DataError("nothing to resume (no config.json)", paths.root)
    saved, _ = read_config(paths)
    det_cfg = saved.detector
    cfg = dataclasses.replace(saved.train, epochs=cfg.epochs)
    split = read_split(paths)
    if split is not None and split.get("val") is not None and val_dataset is None:
        return (det_cfg, cfg, dataset.subset(split["train"]),
                dataset.subset(split["val"]) if split["val"] else None)
    return (det_cfg, cfg, *prepare_split(dataset, cfg, val_dataset))


def _train_epoch(step_fn, state, batches, steps: int):
    """Run up to ``steps`` batches; ``(state, mean of each metric)``."""
    sums: dict[str, float] = {}
    n = 0
    for b, batch in enumerate(batches):
        if b >= steps:
            break
        state, metrics = step_fn(state, jnp.asarray(batch.images), jnp.asarray(batch.targets))
        for k, v in jax.device_get(metrics).items():
            sums[k] = sums.get(k, 0.0) + float(v)
        n += 1
    return state, {k: v / max(n, 1) for k, v in sums.items()}


def train(dataset: DetectionDataset | str | Path, det_cfg: DetectorConfig, cfg: TrainConfig,
          out_dir: str | Path, *, resume: bool = False, val_dataset: DetectionDataset | None =
          None, data_format: str | None = None, progress: Callable | None = None,
          log: Callable[[str], None] | None = None, max_steps_per_epoch: int | None = None,
          stop_after: int | None = None,
          on_epoch: Callable[[list[dict], DetectorConfig], None] | None = None) -> dict:
    """Train ``det_cfg`` on ``dataset`` with ``cfg``; write the run folder ``out_dir``.

    Args:
        dataset: a data set or a folder (read with ``data_format``, auto-detected).
        det_cfg: the model; ``num_classes`` is taken from the data set.
        resume: continue from ``out_dir/checkpoints/last`` (the saved config and split are
            used; ``cfg.epochs`` may be raised to train longer).
        val_dataset: evaluate on this instead of the fixed split.
        progress: ``progress(iterable, total=..., desc=...)`` wrapper (e.g. tqdm).
        log: called with one line per epoch.
        max_steps_per_epoch: cap batches per epoch (tests, smoke runs).
        stop_after: stop after this many epochs of this call (checkpoint written), as if
            interrupted; ``resume=True`` continues (the schedule is that of ``cfg.epochs``).
        on_epoch: called after each epoch's checkpoint and metrics with the history so far
            (one dict per epoch, as in ``metrics.json``) and the resolved detector config;
            e.g. :func:`uavcal_jax.plots.training_curves_writer` draws ``curves.png``.

    Returns a summary dict: run folder, epochs, best epoch and its scores, final losses.
    """
    paths = RunPaths(Path(out_dir))
    if isinstance(dataset, str | Path):
        dataset = load_dataset(dataset, data_format)
    if len(dataset) == 0:
        raise DataError("the data set has no images", dataset.root)
    det_cfg = det_cfg.replace(num_classes=max(1, dataset.num_classes))
    det_cfg, cfg, train_set, val_set = _resolve(paths, dataset, det_cfg, cfg, resume,
                                                val_dataset, log)
    paths.root.mkdir(parents=True, exist_ok=True)
    write_config(paths, det_cfg, cfg, {
        "root": str(Path(dataset.root).absolute()), "format": dataset.format,
        "class_names": list(dataset.class_names), "category_ids": list(dataset.category_ids),
        "num_train": len(train_set), "num_val": len(val_set) if val_set else 0,
        "external_val": val_dataset is not None})
    if not (resume and paths.split.is_file()):
        save_split(paths.split, train_set.image_ids, val_set.image_ids if val_set else [],
                   val_fraction=cfg.val_fraction, seed=cfg.split_seed,
                   external_val=val_dataset is not None)

    loader = DetectionLoader(train_set, det_cfg.img_size, cfg.batch_size, augment=cfg.augment,
                             shuffle=True, seed=cfg.seed, drop_last=True, cache=cfg.cache,
                             workers=cfg.workers)
    steps_per_epoch = len(loader) if max_steps_per_epoch is None else min(
        len(loader), max_steps_per_epoch)
    val_loader = (DetectionLoader(val_set, det_cfg.img_size, cfg.batch_size, cache=cfg.cache,
                                  workers=cfg.workers, include_difficult=True)
                  if val_set is not None and len(val_set) else None)
    # the step does not depend on the epoch budget except through the schedule
    tx, step_fn = compiled_training(det_cfg, cfg, steps_per_epoch)
    state = init_train_state(jax.random.PRNGKey(cfg.seed), det_cfg, tx)
    last = Checkpoints(paths.checkpoints("last"), max_to_keep=1)
    best = Checkpoints(paths.checkpoints("best"), max_to_keep=1)
    history: list[dict] = []
    start_epoch, best_score, best_epoch = 0, -math.inf, None
    if resume and last.latest_step() is not None:
        state, meta = last.restore(state)
        history = meta["history"]
        start_epoch = int(meta["epoch"]) + 1
        if meta.get("best_score") is not None:
            best_score = float(meta["best_score"])
        best_epoch = meta.get("best_epoch")
        loader.load_state_dict(meta["loader"])
    loader.next_epoch = start_epoch
    predict_fn = make_predict_fn(det_cfg, cfg.predict) if val_loader else None
    wrap = progress or (lambda it, **kw: it)

    try:
        end_epoch = cfg.epochs if stop_after is None else min(cfg.epochs,
                                                             start_epoch + stop_after)
        for epoch in range(start_epoch, end_epoch):
            t0 = time.perf_counter()
            batches = loader.epoch(epoch)
            state, means = _train_epoch(step_fn, state, wrap(
                batches, total=steps_per_epoch, desc=f"epoch {epoch + 1}/{cfg.epochs}"),
                steps_per_epoch)
            batches.close()
            loader.next_epoch = epoch + 1
            row: dict[str, Any] = {"epoch": epoch + 1,
                                   "lr": current_lr(cfg, steps_per_epoch, int(state.step) - 1),
                                   **means}
            if not all(math.isfinite(v) for v in means.values()):
                raise FloatingPointError(f"non-finite training loss at epoch {epoch + 1}: "
                                         f"{row}")
            row["train_time_s"] = time.perf_counter() - t0
            score = None
            if val_loader is not None and ((epoch + 1) % cfg.eval_every == 0
                                           or epoch + 1 == cfg.epochs):
                t1 = time.perf_counter()
                dets = predict_dataset(functools.partial(predict_fn, state.variables(cfg.ema)),
                                       val_loader)
                result = evaluate_predictions(val_loader.records, dets, det_cfg.num_classes,
                                              cfg.map_max_dets)
                row["map50"], row["map50_95"] = result.map50, result.map50_95
                row["eval_time_s"] = time.perf_counter() - t1
                score = fitness(result, cfg.select_metric)
            improved = (score is not None and score > best_score) or (
                val_loader is None and epoch + 1 == cfg.epochs)
            if improved:
                best_score = score if score is not None else best_score
                best_epoch = epoch + 1
            history.append(row)
            meta = {"epoch": epoch, "history": history,
                    "best_score": None if best_score == -math.inf else best_score,
                    "best_epoch": best_epoch, "loader": loader.state_dict(),
                    "steps_per_epoch": steps_per_epoch}
            if improved:
                best.save(epoch + 1, state.variables(cfg.ema),
                          {**meta, "select_metric": cfg.select_metric})
            last.save(epoch + 1, state, meta)
            write_metrics(paths, history, best_epoch, best_score, cfg.select_metric)
            if on_epoch is not None:
                on_epoch(history, det_cfg)
            if log is not None:
                log(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                for k, v in row.items()}))
    finally:
        loader.close()
        if val_loader is not None:
            val_loader.close()
        last.close()
        best.close()

    if best_epoch is None and history and len(history) == cfg.epochs:
        # validation never ran: keep the last weights
        with Checkpoints(paths.checkpoints("best"), max_to_keep=1) as ck:
            ck.save(len(history), state.variables(cfg.ema), {"epoch": len(history) - 1,
                                                             "history": history})
            best_epoch = len(history)
    final = history[-1] if history else {}
    best_row = next((r for r in history if r["epoch"] == best_epoch), {})
    return {
        "run": str(paths.root), "model": det_cfg.model, "epochs": len(history),
        "steps": int(state.step), "best_epoch": best_epoch,
        "select_metric": cfg.select_metric,
        "map50": best_row.get("map50"), "map50_95": best_row.get("map50_95"),
        "final_loss": final.get("loss"), "num_train": len(train_set),
        "num_val": len(val_set) if val_set else 0,
    }
