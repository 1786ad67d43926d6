"""A training run's folder: its paths, what training writes there, and reading it back.

Run folder::

    config.json     the resolved DetectConfig (detector, train) and the data set's info (data)
    split.json      the train/val image ids (the fixed split; eval reuses it)
    metrics.jsonl   one row per epoch (losses, lr, map50, map50_95, time; :mod:`uavcal_jax.runs`)
    metrics.csv     the same rows as a table
    metrics.json    the same rows, plus the best epoch and scores
    curves.png      loss and mAP curves (drawn by the caller's per-epoch callback,
                    :func:`uavcal_jax.plots.training_curves_writer`)
    checkpoints/last/<epoch>/  full train state + meta (resume; :mod:`uavcal_jax.runs`)
    checkpoints/best/<epoch>/  EMA variables of the best epoch + meta
    export/detector.jax        the exported predict function (written by ``uavcal detect``)

:func:`export_run` cuts a run down to what predicting needs (``config.json``, ``metrics.json``
and the best checkpoint), as the shipped weights are. Only :func:`load_run` needs the model; it is
imported when called.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

from uavcal_jax import config as config_io
from uavcal_jax.detect.config import DetectConfig, DetectorConfig, TrainConfig
from uavcal_jax.errors import DataError
from uavcal_jax.runs import CONFIG_FILE, KINDS, Checkpoints, RunSpec, write_folder


@dataclass(frozen=True)
class RunPaths:
    """The files of a run folder ``root``."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / CONFIG_FILE

    @property
    def split(self) -> Path:
        return self.root / "split.json"

    @property
    def csv(self) -> Path:
        return self.root / "metrics.csv"

    @property
    def json(self) -> Path:
        return self.root / "metrics.json"

    @property
    def png(self) -> Path:
        return self.root / "curves.png"

    @property
    def export(self) -> Path:
        return self.root / "export" / "detector.jax"

    def checkpoints(self, which: str) -> Path:
        """``checkpoints/best`` or ``checkpoints/last``."""
        if which not in KINDS:
            raise ValueError(f"which must be one of {KINDS}, not {which!r}")
        return self.root / "checkpoints" / which


#: The top-level entry of ``config.json`` beside the :class:`DetectConfig` tree.
DATA_KEY = "data"


#: Settings a resumed run may change: the epoch budget (the schedule is that of the new one).
RESUMABLE_KEYS = frozenset({"train.epochs"})


def run_spec(det_cfg: DetectorConfig, cfg: TrainConfig, data: dict,
             steps_per_epoch: int | None = None) -> RunSpec:
    """The run folder's record (:class:`uavcal_jax.runs.RunSpec`): ``config.json`` holds
    the resolved :class:`DetectConfig` and the data set's description (``data``); each
    checkpoint the configuration, the batches per epoch and the selection metric."""
    config = DetectConfig(det_cfg, cfg)
    return RunSpec(config=config, resolved=config_io.to_dict(config),
                   extras={DATA_KEY: data}, ignore=RESUMABLE_KEYS, keep=1,
                   meta={"steps_per_epoch": steps_per_epoch,
                         "select_metric": cfg.select_metric})


def write_config(paths: RunPaths, det_cfg: DetectorConfig, cfg: TrainConfig, data: dict
                 ) -> None:
    """``config.json`` as training writes it (:func:`run_spec`)."""
    spec = run_spec(det_cfg, cfg, data)
    config_io.write_config(paths.config, spec.config, **spec.extras)


def read_config(paths: RunPaths) -> tuple[DetectConfig, dict]:
    """The run's :class:`DetectConfig` and its data set's description."""
    if not paths.config.is_file():
        raise DataError("not a training run (no config.json)", paths.root)
    config = config_io.read_config(paths.config, DetectConfig, ignore=(DATA_KEY,))
    return config, json.loads(paths.config.read_text())[DATA_KEY]


def read_split(paths: RunPaths) -> dict | None:
    return json.loads(paths.split.read_text()) if paths.split.is_file() else None


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    keys = list(rows[0].keys())
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})


def write_metrics(paths: RunPaths, history: list[dict], best_epoch: int | None,
                  best_score: float | None, select_metric: str) -> None:
    """``metrics.csv`` and ``metrics.json`` of the epochs so far."""
    _write_csv(paths.csv, history)
    paths.json.write_text(json.dumps({
        "history": history, "best_epoch": best_epoch,
        "best_score": None if best_score is None or best_score == -math.inf else best_score,
        "select_metric": select_metric}, indent=1))


def export_run(run: str | Path, target: str | Path, which: str = "best", *,
               params_dtype: str | None = None, extra: dict[str, dict] | None = None) -> Path:
    """Write ``target``: ``run``'s ``config.json``, ``metrics.json`` and its ``which``
    checkpoint only (no optimiser state, split or export), plus ``extra`` JSON files
    (``{"eval.json": {...}}``). It restores like the run (:func:`load_run` with ``which``)
    but does not resume training.

    ``params_dtype`` (``"float16"``; ``which="best"`` only) stores the parameters in that
    type, halving the folder; the batch statistics stay float32 and :func:`load_run` casts
    back to the model's float32 (weights rounded to 11 significant bits, about 3 decimal
    digits). Written into a temporary sibling and renamed, so ``target`` is whole or absent.
    """
    src, target = RunPaths(Path(run)), Path(target)
    if not src.config.is_file() or not src.checkpoints(which).is_dir():
        raise DataError(f"not a training run with a {which} checkpoint", src.root)
    if params_dtype is not None and which != "best":
        raise ValueError("params_dtype applies to the best checkpoint (variables) only")

    def fill(folder: Path) -> None:
        out = RunPaths(folder)
        out.checkpoints(which).parent.mkdir(parents=True)
        shutil.copy2(src.config, out.config)
        if src.json.is_file():
            shutil.copy2(src.json, out.json)
        if params_dtype is None:
            shutil.copytree(src.checkpoints(which), out.checkpoints(which))
        else:
            import jax
            import numpy as np

            loaded = load_run(src.root, which)
            params = jax.tree.map(lambda x: np.asarray(x).astype(params_dtype),
                                  loaded.variables["params"])
            with Checkpoints(folder, kinds=(which,)) as ck:
                ck.save(which, loaded.meta["epoch"],
                        {"params": params, "batch_stats": loaded.variables["batch_stats"]},
                        {**loaded.meta, "params_dtype": params_dtype})
        for name, obj in (extra or {}).items():
            (folder / name).write_text(json.dumps(obj, indent=1))

    return write_folder(target, fill)


@dataclass(frozen=True)
class LoadedRun:
    """A trained run read back: configs, data info, split and the chosen variables."""

    run: Path
    det_cfg: DetectorConfig
    train_cfg: TrainConfig
    data: dict
    split: dict | None
    variables: dict
    meta: dict


def load_run(run: str | Path, which: str = "best") -> LoadedRun:
    """Read a run folder written by :func:`~uavcal_jax.detect.train.train` (``which``:
    ``"best"``, the EMA variables of the best epoch, or ``"last"``)."""
    import jax

    from uavcal_jax.detect.optim import make_optimizer
    from uavcal_jax.detect.step import abstract_variables, init_train_state

    paths = RunPaths(Path(run))
    config, data = read_config(paths)
    det_cfg, train_cfg = config.detector, config.train
    abstract = abstract_variables(det_cfg)
    with Checkpoints(paths.root, read_only=True, kinds=(which,)) as ck:
        if which == "best":
            variables, meta = ck.restore(which, abstract)
        else:
            tx = make_optimizer(train_cfg, 1, abstract["params"])
            st_abs = jax.eval_shape(lambda: init_train_state(jax.random.PRNGKey(0), det_cfg,
                                                             tx))
            state, meta = ck.restore(which, st_abs)
            variables = state.variables(train_cfg.ema)
    return LoadedRun(paths.root, det_cfg, train_cfg, data, read_split(paths),
                     variables, meta)
