"""A training run's folder: its paths, what training writes there, and reading it back.

Run folder::

    config.json     resolved detector + train config, data set info
    split.json      the train/val image ids (the fixed split; eval reuses it)
    metrics.csv     one row per epoch (losses, lr, map50, map50_95, time)
    metrics.json    the same rows, plus the best epoch and scores
    curves.png      loss and mAP curves
    checkpoints/last/<epoch>/  full train state + meta (resume)
    checkpoints/best/<epoch>/  EMA variables of the best epoch + meta
    export/detector.jax        the exported predict function (written by ``uavcal detect``)

Only :func:`load_run` needs the model and orbax; they are imported when it is called, so the
paths and constants here are cheap to import (the CLI builds its parser from them).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uavcal_jax.detect.config import DetectorConfig, TrainConfig
from uavcal_jax.errors import DataError

#: The checkpoints a run keeps: the best EMA weights and the last full train state.
CHECKPOINTS = ("best", "last")


@dataclass(frozen=True)
class RunPaths:
    """The files of a run folder ``root``."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.json"

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
        if which not in CHECKPOINTS:
            raise ValueError(f"which must be one of {CHECKPOINTS}, not {which!r}")
        return self.root / "checkpoints" / which


def write_config(paths: RunPaths, det_cfg: DetectorConfig, cfg: TrainConfig, data: dict
                 ) -> None:
    """``config.json``: the resolved configurations and the data set's description."""
    doc = {"detector": det_cfg.to_dict(), "train": cfg.to_dict(), "data": data}
    paths.config.write_text(json.dumps(doc, indent=1))


def read_config(paths: RunPaths) -> dict:
    if not paths.config.is_file():
        raise DataError("not a training run (no config.json)", paths.root)
    return json.loads(paths.config.read_text())


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


def plot_curves(path: Path, rows: list[dict], title: str = "") -> None:
    """Loss and mAP per epoch into a PNG (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [r["epoch"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    for key in ("loss", "box", "obj", "cls"):
        if any(key in r for r in rows):
            ax1.plot(epochs, [r.get(key, np.nan) for r in rows], label=key)
    ax1.set_xlabel("epoch")
    ax1.set_ylabel("train loss")
    ax1.set_yscale("log")
    ax1.legend()
    for key in ("map50", "map50_95"):
        xs = [r["epoch"] for r in rows if r.get(key) is not None]
        ax2.plot(xs, [r[key] for r in rows if r.get(key) is not None], "o-", label=key)
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("validation mAP")
    ax2.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_metrics(paths: RunPaths, history: list[dict], best_epoch: int | None,
                  best_score: float | None, select_metric: str, title: str = "") -> None:
    """``metrics.csv``, ``metrics.json`` and ``curves.png`` of the epochs so far."""
    _write_csv(paths.csv, history)
    paths.json.write_text(json.dumps({
        "history": history, "best_epoch": best_epoch,
        "best_score": None if best_score is None or best_score == -math.inf else best_score,
        "select_metric": select_metric}, indent=1))
    try:
        plot_curves(paths.png, history, title=title)
    except Exception as err:  # noqa: BLE001 - a plot must never stop training
        paths.png.with_suffix(".txt").write_text(f"plot failed: {err}\n")


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

    from uavcal_jax.detect.checkpoint import Checkpoints
    from uavcal_jax.detect.optim import make_optimizer
    from uavcal_jax.detect.step import abstract_variables, init_train_state

    paths = RunPaths(Path(run))
    doc = read_config(paths)
    det_cfg = DetectorConfig.from_dict(doc["detector"])
    train_cfg = TrainConfig.from_dict(doc["train"])
    abstract = abstract_variables(det_cfg)
    with Checkpoints(paths.checkpoints(which), read_only=True) as ck:
        if which == "best":
            variables, meta = ck.restore(abstract)
        else:
            tx = make_optimizer(train_cfg, 1, abstract["params"])
            st_abs = jax.eval_shape(lambda: init_train_state(jax.random.PRNGKey(0), det_cfg,
                                                             tx))
            state, meta = ck.restore(st_abs)
            variables = state.variables(train_cfg.ema)
    return LoadedRun(paths.root, det_cfg, train_cfg, doc["data"], read_split(paths),
                     variables, meta)
