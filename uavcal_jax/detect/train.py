"""Training the detector: its data, step, validation mAP and metric tables given to the
run framework (:mod:`uavcal_jax.runs`: run folder, checkpoints, resume, the epoch loop).

The numerics live elsewhere and are pure: the optimiser in :mod:`.optim`, the jitted step and
its EMA in :mod:`.step`, prediction in :mod:`.predict`, the mAP in :mod:`.metrics`; the run
folder's detector files are :mod:`.run`'s.

Best model: after each evaluation the EMA weights are scored on the validation split by
``TrainConfig.select_metric`` (default ``map50_95``; ``map50`` or YOLOv5's
``fitness = 0.1 map50 + 0.9 map50_95``) and the best are saved to ``checkpoints/best``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp

from uavcal_jax.data.detection_records import DetectionDataset
from uavcal_jax.detect.anchors import check_anchors, label_sizes
from uavcal_jax.detect.config import DetectorConfig, TrainConfig
from uavcal_jax.detect.datasets import load_dataset, save_split, split_ids
from uavcal_jax.detect.loader import DetectionLoader
from uavcal_jax.detect.metrics import evaluate_predictions, fitness
from uavcal_jax.detect.optim import current_lr
from uavcal_jax.detect.predict import make_predict_fn, predict_dataset
from uavcal_jax.detect.run import RunPaths, read_config, read_split, run_spec, write_metrics
from uavcal_jax.detect.step import TrainState, compiled_training, init_train_state
from uavcal_jax.errors import DataError
from uavcal_jax.runs import Best, Loop, Selection, train_epochs


def prepare_split(dataset: DetectionDataset, cfg: TrainConfig, val_dataset=None):
    """``(train, val)`` data sets: ``val_dataset`` if given, else the fixed split."""
    if val_dataset is not None:
        return dataset, val_dataset
    if cfg.val_fraction <= 0:
        return dataset, None
    train_ids, val_ids = split_ids(dataset.image_ids, cfg.val_fraction, cfg.split_seed)
    return dataset.subset(train_ids), dataset.subset(val_ids)


def starting_weights(cfg: TrainConfig, dataset: DetectionDataset):
    """``(detector config, variables)`` of ``cfg.init_from`` (fine-tuning), or ``None``.

    Raises:
        DataError: the run is unreadable, or ``dataset`` names other classes than it."""
    if cfg.init_from is None:
        return None
    from uavcal_jax.detect.run import load_run

    source = load_run(cfg.init_from)
    names = list(source.data.get("class_names") or [])
    if names and names != list(dataset.class_names):
        raise DataError(f"the data set's classes {list(dataset.class_names)} are not the "
                        f"classes {names} of the weights to fine-tune", Path(cfg.init_from))
    return source.det_cfg, source.variables


def initial_state(det_cfg: DetectorConfig, cfg: TrainConfig, tx, variables: dict | None
                  ) -> TrainState:
    """A fresh run's state: random weights from ``cfg.seed``, or ``variables`` (``{"params",
    "batch_stats"}``, :func:`starting_weights`') as both the weights and their EMA."""
    state = init_train_state(jax.random.PRNGKey(cfg.seed), det_cfg, tx)
    if variables is None:
        return state
    params, stats = variables["params"], variables["batch_stats"]
    copy = lambda tree: jax.tree.map(jnp.array, tree)  # noqa: E731 - own buffers (donation)
    return state._replace(params=copy(params), batch_stats=copy(stats),
                          opt_state=tx.init(params), ema_params=copy(params),
                          ema_batch_stats=copy(stats))


def _resolve(paths: RunPaths, dataset: DetectionDataset, det_cfg: DetectorConfig,
             cfg: TrainConfig, resume: bool, val_dataset, log, start):
    """The configurations and the (train, val) sets of this call: the saved ones when
    resuming (``cfg.epochs`` may be raised), else fresh ones with autoanchor (or the model
    of ``cfg.init_from`` when fine-tuning)."""
    if not resume:
        train_set, val_set = prepare_split(dataset, cfg, val_dataset)
        if start is not None:  # fine-tuning: the source's model (``starting_weights``)
            return start[0], cfg, train_set, val_set
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


def train(dataset: DetectionDataset | str | Path, det_cfg: DetectorConfig, cfg: TrainConfig,
          out_dir: str | Path, *, resume: bool = False, val_dataset: DetectionDataset | None =
          None, data_format: str | None = None, progress: bool = False,
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
        progress: a bar per epoch on stderr.
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
    # the source run is read once: its model here, its weights in ``init`` (a fresh run only)
    start = None if resume else starting_weights(cfg, dataset)
    det_cfg, cfg, train_set, val_set = _resolve(paths, dataset, det_cfg, cfg, resume,
                                                val_dataset, log, start)
    crops = cfg.augment is not None and cfg.augment.crop_scale is not None
    loader = DetectionLoader(train_set, cfg.augment.crop_size if crops else det_cfg.img_size,
                             cfg.batch_size, augment=cfg.augment,
                             shuffle=True, seed=cfg.seed, drop_last=True, cache=cfg.cache,
                             workers=cfg.workers)
    steps_per_epoch = len(loader) if max_steps_per_epoch is None else min(
        len(loader), max_steps_per_epoch)
    val_loader = (DetectionLoader(val_set, det_cfg.img_size, cfg.batch_size, cache=cfg.cache,
                                  workers=cfg.workers, include_difficult=True)
                  if val_set is not None and len(val_set) else None)
    # the step does not depend on the epoch budget except through the schedule, nor on where
    # the weights started (one compilation for a run and its fine-tuning)
    tx, step_fn = compiled_training(det_cfg, dataclasses.replace(cfg, init_from=None),
                                    steps_per_epoch)
    predict_fn = make_predict_fn(det_cfg, cfg.predict) if val_loader else None

    def init() -> TrainState:  # a fresh run: its split, then its state
        save_split(paths.split, train_set.image_ids, val_set.image_ids if val_set else [],
                   val_fraction=cfg.val_fraction, seed=cfg.split_seed,
                   external_val=val_dataset is not None)
        return initial_state(det_cfg, cfg, tx, None if start is None else start[1])

    def batches(epoch: int):
        stream = loader.epoch(epoch)
        try:
            for batch in itertools.islice(stream, steps_per_epoch):
                yield (jnp.asarray(batch.images), jnp.asarray(batch.targets)), 1
        finally:
            stream.close()

    def row(state: TrainState, means: dict) -> dict:
        return {"lr": current_lr(cfg, steps_per_epoch, int(state.step) - 1), **means}

    def validate(state: TrainState, epoch: int) -> dict:
        if (epoch + 1) % cfg.eval_every and epoch + 1 != cfg.epochs:
            return {}
        dets = predict_dataset(functools.partial(predict_fn, state.variables(cfg.ema)),
                               val_loader)
        result = evaluate_predictions(val_loader.records, dets, det_cfg.num_classes,
                                      cfg.map_max_dets)
        return {"map50": result.map50, "map50_95": result.map50_95}

    def after_epoch(history: list[dict], best: Best) -> None:
        write_metrics(paths, history, best.epoch, best.score, cfg.select_metric)
        if on_epoch is not None:
            on_epoch(history, det_cfg)
        if log is not None:
            log(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                            for k, v in history[-1].items()}))

    spec = run_spec(det_cfg, cfg, {
        "root": str(Path(dataset.root).absolute()), "format": dataset.format,
        "class_names": list(dataset.class_names), "category_ids": list(dataset.category_ids),
        "num_train": len(train_set), "num_val": len(val_set) if val_set else 0,
        "external_val": val_dataset is not None}, steps_per_epoch)
    loop = Loop(epochs=cfg.epochs, steps=steps_per_epoch, batches=batches,
                step=lambda state, batch: step_fn(state, *batch), row=row,
                evaluate=validate if val_loader is not None else None,
                selection=Selection(lambda r: fitness(r, cfg.select_metric)
                                    if "map50" in r else None, maximize=True),
                best=lambda state: state.variables(cfg.ema))
    try:
        result = train_epochs(
            paths.root, spec, loop, init,
            lambda: jax.eval_shape(lambda: init_train_state(jax.random.PRNGKey(cfg.seed),
                                                            det_cfg, tx)),
            resume=resume, stop_after=stop_after, progress=progress, on_epoch=after_epoch)
    finally:
        loader.close()
        if val_loader is not None:
            val_loader.close()
    history, state = result.history, result.state
    final = history[-1] if history else {}
    best_row = next((r for r in history if r["epoch"] == result.best.epoch), {})
    return {
        "run": str(paths.root), "model": det_cfg.model, "epochs": len(history),
        "steps": int(state.step), "best_epoch": result.best.epoch,
        "select_metric": cfg.select_metric,
        "map50": best_row.get("map50"), "map50_95": best_row.get("map50_95"),
        "final_loss": final.get("loss"), "num_train": len(train_set),
        "num_val": len(val_set) if val_set else 0,
    }
