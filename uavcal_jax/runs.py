"""One training-run framework for every model: the run folder, atomic orbax best/last
checkpoints, exact resume and an epoch loop over the caller's pure ``step`` and ``evaluate``.

Run folder ``RUN``::

    config.json                 the resolved configuration and the caller's extras
    metrics.jsonl               one JSON row per epoch (:func:`train_epochs`)
    checkpoints/last/<epoch>/   the newest ``keep`` epochs: the full training state (resume)
    checkpoints/best/<epoch>/   the epoch the selection metric liked best

A task package adds its own files (the detector its split and metric tables) and keeps what
is its own: models, data, metrics. Each checkpoint step has two items: ``state``, a pytree of
arrays (orbax ``StandardSave``), and ``meta``, a JSON dict: ``epoch`` (epochs trained, the
step's number), ``position`` (where the data stream continues), ``early_stopping`` (the
selection record), ``stopped``, ``config`` (the resolved configuration), the caller's extras
and :data:`FORMAT_VERSION`.

Atomicity: orbax writes a step into a temporary folder and renames it when complete, so a run
killed mid-save leaves only the temporary folder, which :meth:`Checkpoints.latest` never
returns; a metrics row is appended before its epoch's checkpoint, and a resumed run drops the
rows newer than its checkpoint. Restoring against a configuration checks the format version
and the saved configuration *before* reading arrays: another one gives one line naming the
run folder and what differs (:class:`~uavcal_jax.errors.DataError`), not an orbax trace.

Exact resume: the data of an epoch is a pure function of the epoch (:class:`Loop`), so the
checkpoint's position is the data stream's whole state, and a run stopped after any epoch and
resumed trains on what the uninterrupted run trained on.

One module over 450 lines, one job: a run folder's life, from its checkpoints and metrics rows
to where an evaluation of it may write (:func:`results_folder`). The loop relies on every rule
of the folder, so they stay in one place.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp
from absl import logging as absl_logging

from uavcal_jax.config import write_config
from uavcal_jax.errors import DataError
from uavcal_jax.progress import progress as progress_bar

__all__ = ["CONFIG_FILE", "FORMAT_VERSION", "KINDS", "METRICS_FILE", "Best", "Checkpoints",
           "EVAL_HOME", "Loop", "RunResult", "RunSpec", "Selection", "config_differences",
           "read_metrics", "results_folder", "results_redirect", "train_epochs",
           "write_folder"]

#: A run folder's configuration.
CONFIG_FILE = "config.json"
#: A run folder's per-epoch record, one JSON row per epoch.
METRICS_FILE = "metrics.jsonl"
#: Version of the checkpoint layout (items, meta keys); bump on an incompatible change.
FORMAT_VERSION = 2
#: The two checkpoint series of a run (the first is what inference reads by default).
KINDS = ("best", "last")
#: Where the evaluation of a run that must not be written into goes, relative to the current
#: folder: ``uavcal_eval/<run name>`` (see :func:`results_folder`).
EVAL_HOME = Path("uavcal_eval")
#: The installed package: the weights shipped in it are read, never written.
_PACKAGE = Path(__file__).resolve().parent


# ------------------------------------------------------------------------ results folder

def results_redirect(run: str | Path) -> str | None:
    """Why the results of evaluating ``run`` must not go into ``run`` (``None``: they may).

    Not into a folder inside the installed ``uavcal_jax`` package (the shipped weights: in
    site-packages after ``pip install .``, and one user's evaluation must not change what every
    user reads as the weights' scores), nor into a folder that is not writable.
    """
    run = Path(run).resolve()
    if run == _PACKAGE or _PACKAGE in run.parents:
        return "is inside the installed uavcal_jax package (shipped weights)"
    if not os.access(run, os.W_OK):
        return "is not writable"
    return None


def results_folder(run: str | Path, out: str | Path | None = None) -> Path:
    """The folder the results of evaluating ``run`` go to: ``out`` when given; else ``run``
    itself, unless :func:`results_redirect` says no: then ``EVAL_HOME/<run name>`` in the
    current folder. The folder is not created here."""
    if out is not None:
        return Path(out)
    if results_redirect(run) is None:
        return Path(run)
    return EVAL_HOME / Path(run).resolve().name


# ----------------------------------------------------------------------------- checkpoints

def _as_json(value: Any) -> Any:
    """``value`` as a JSON round trip reads it back: tuples, nested ones too, as lists."""
    if isinstance(value, tuple | list):
        return [_as_json(v) for v in value]
    return value


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, Mapping):
        out: dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: _as_json(tree)}


def config_differences(saved: Mapping, wanted: Mapping, ignore: frozenset[str] = frozenset(),
                       defaults: Mapping | None = None) -> list[str]:
    """``"key: saved -> wanted"`` for every flattened key whose value differs (missing keys
    show as ``None``), except those in ``ignore``. A key ``saved`` lacks takes its value in
    ``defaults`` when given: a setting added after the checkpoint was written, whose default
    is the behaviour the checkpoint was trained with."""
    a, b = {**_flatten(defaults or {}), **_flatten(saved)}, _flatten(wanted)
    return [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b))
            if k not in ignore and a.get(k) != b.get(k)]


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}"


@contextlib.contextmanager
def _quiet_orbax(quiet: bool):
    if not quiet:
        yield
        return
    before = absl_logging.get_verbosity()
    absl_logging.set_verbosity(absl_logging.ERROR)
    try:
        yield
    finally:
        absl_logging.set_verbosity(before)


class Checkpoints:
    """The ``best`` and ``last`` checkpoint series of run folder ``run_dir`` (``kinds``: the
    series to open). ``last`` keeps the newest ``keep`` epochs, ``best`` one. Read-only, a
    folder may hold one series only (shipped weights keep ``best``)."""

    def __init__(self, run_dir: str | Path, keep: int = 2, read_only: bool = False,
                 kinds: Iterable[str] = KINDS):
        self.run_dir = Path(run_dir).absolute()
        self._managers: dict[str, ocp.CheckpointManager] = {}
        for kind in kinds:
            folder = self.run_dir / "checkpoints" / kind
            if read_only and not folder.is_dir():
                continue
            # read-only managers never delete, and orbax warns unless max_to_keep is None
            kept = None if read_only else (keep if kind == "last" else 1)
            with _quiet_orbax(read_only):  # orbax warns that read-only means read-only
                options = ocp.CheckpointManagerOptions(
                    max_to_keep=kept, create=not read_only, read_only=read_only,
                    enable_async_checkpointing=False)
                self._managers[kind] = ocp.CheckpointManager(folder, options=options,
                                                             item_names=("state", "meta"))
        if not self._managers:
            raise DataError("no checkpoints (not a run folder?)", self.run_dir)

    def _manager(self, kind: str) -> ocp.CheckpointManager:
        if kind not in self._managers:
            raise DataError(f"no {kind} checkpoints in this run folder", self.run_dir)
        return self._managers[kind]

    def save(self, kind: str, epoch: int, tree: Any, meta: dict) -> None:
        """Write epoch ``epoch`` of series ``kind`` (``meta`` gets the format version) and
        wait until it is renamed into place."""
        meta = {**meta, "format_version": FORMAT_VERSION}
        manager = self._manager(kind)
        manager.save(int(epoch), args=ocp.args.Composite(
            state=ocp.args.StandardSave(tree), meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()

    def latest(self, kind: str = "last") -> int | None:
        """The newest complete epoch of ``kind``, ``None`` when there is none."""
        return self._manager(kind).latest_step()

    def read_meta(self, kind: str = "last", epoch: int | None = None) -> tuple[int, dict]:
        """``(epoch, meta)`` of a saved step (default the newest); ``meta["epoch"]`` is the
        step's number, the epochs trained (detector checkpoints written before this module
        counted from 0)."""
        manager = self._manager(kind)
        epoch = manager.latest_step() if epoch is None else epoch
        if epoch is None:
            raise DataError(f"no {kind} checkpoint saved yet", self.run_dir)
        try:
            out = manager.restore(epoch, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except Exception as err:  # orbax raises many types for a damaged step
            raise DataError(f"{kind} checkpoint {epoch} is unreadable ({_first_line(err)})",
                            self.run_dir) from None
        return epoch, {**out["meta"], "epoch": int(epoch)}

    def restore(self, kind: str, abstract_tree: Any, config: Mapping | None = None, *,
                epoch: int | None = None, ignore: frozenset[str] = frozenset(),
                defaults: Mapping | None = None,
                layout: Callable[[Mapping], Mapping] | None = None) -> tuple[Any, dict]:
        """``(tree, meta)`` of a saved step into the structure of ``abstract_tree`` (arrays
        or ``jax.ShapeDtypeStruct``). With ``config`` (the resolved configuration wanted),
        first check that the step was written with :data:`FORMAT_VERSION` and that
        configuration (:func:`config_differences` with ``ignore`` and ``defaults``; ``layout``
        reads saved configurations of an older layout into the current one).

        Raises:
            DataError: no checkpoint, another format version, another configuration, or a
                damaged step; one line naming the run folder.
        """
        epoch, meta = self.read_meta(kind, epoch)
        if config is not None:
            version = meta.get("format_version")
            if version != FORMAT_VERSION:
                raise DataError(f"{kind} checkpoint {epoch} has format version {version}, "
                                f"this version reads {FORMAT_VERSION}", self.run_dir)
            saved = meta.get("config", {})
            diff = config_differences(layout(saved) if layout else saved, config, ignore,
                                      defaults)
            if diff:
                raise DataError(f"{kind} checkpoint {epoch} was written with another "
                                f"configuration ({'; '.join(diff)})", self.run_dir)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_tree)
        try:
            out = self._manager(kind).restore(epoch, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract)))
        except Exception as err:
            raise DataError(f"{kind} checkpoint {epoch} does not restore "
                            f"({_first_line(err)})", self.run_dir) from None
        return out["state"], meta

    def close(self) -> None:
        for manager in self._managers.values():
            manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_folder(target: str | Path, fill: Callable[[Path], None]) -> Path:
    """Write the folder ``target`` whole or not at all: ``fill(tmp)`` fills an empty
    temporary sibling, which then replaces ``target``. Returns ``target``."""
    target = Path(target)
    tmp = target.with_name(f".{target.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    fill(tmp)
    shutil.rmtree(target, ignore_errors=True)
    tmp.rename(target)
    return target


# ------------------------------------------------------------------------------- selection

class Best(NamedTuple):
    """The selection record: the best score so far (``None``: none yet), the epochs since it
    improved, and the epoch (1-based) that reached it (``None``: none yet)."""

    score: float | None = None
    bad_epochs: int = 0
    epoch: int | None = None


@dataclass(frozen=True)
class Selection:
    """Which epoch is best, and when to stop early.

    ``score(row)``: the epoch's score from its metrics row, ``None`` for an epoch that was
    not scored (it neither improves nor counts toward ``patience``); ``maximize``: higher is
    better; ``patience``: stop after that many scored epochs without an improvement
    (``None``: never). An epoch improves when its score is strictly better (a NaN never is).
    """

    score: Callable[[dict], float | None]
    maximize: bool = False
    patience: int | None = None

    def update(self, best: Best, score: float | None, epoch: int) -> tuple[Best, bool]:
        """The record after ``epoch`` (1-based) scored ``score``, and whether to stop."""
        if score is None:
            return best, False
        ref = best.score if best.score is not None else (-math.inf if self.maximize
                                                         else math.inf)
        if score > ref if self.maximize else score < ref:
            return Best(float(score), 0, epoch), False
        best = Best(best.score, best.bad_epochs + 1, best.epoch)
        return best, self.patience is not None and best.bad_epochs >= self.patience


# ------------------------------------------------------------------------------- the loop

@dataclass(frozen=True)
class RunSpec:
    """What a run folder records and a resume must match.

    ``config``: the configuration tree written to ``config.json`` with the ``extras``
    (top-level entries beside it, e.g. the command line); ``resolved``: the JSON dict each
    checkpoint records and a restore compares (keys in ``ignore`` may differ; keys a saved
    one lacks take their value in ``defaults``; ``layout`` reads older saved layouts);
    ``keep``: ``last`` checkpoints kept; ``meta``: extra entries of every checkpoint's meta.
    """

    config: Any
    resolved: Mapping
    extras: Mapping = field(default_factory=dict)
    ignore: frozenset[str] = frozenset()
    defaults: Mapping | None = None
    layout: Callable[[Mapping], Mapping] | None = None
    keep: int = 2
    meta: Mapping = field(default_factory=dict)


@dataclass(frozen=True)
class Loop:
    """The pure functions a model gives :func:`train_epochs`.

    - ``batches(epoch) -> iterable of (batch, weight)``: epoch ``epoch``'s (0-based) data, a
      pure function of the epoch (the checkpoint's position is all a resume needs);
      ``weight`` (e.g. the batch's real samples) weights its metrics in the epoch's means.
      Closed (``close()``, when it has one) after the epoch.
    - ``step(state, batch) -> (state, metrics)``: one training step; ``metrics`` a dict of
      arrays (scalars or per-seed vectors), averaged over the epoch with the weights.
    - ``row(state, means) -> dict``: the epoch's metrics row entries from those means.
    - ``evaluate(state, epoch) -> dict``: row entries of a validation pass after epoch
      ``epoch`` (0-based), ``{}`` to skip it.
    - ``last(state)`` / ``best(state)``: the pytrees saved as ``last`` (the whole training
      state) and ``best`` (what a model to predict with needs); ``restore(tree)`` inverts
      ``last``.
    """

    epochs: int
    steps: int
    batches: Callable[[int], Iterable[tuple[Any, float]]]
    step: Callable[[Any, Any], tuple[Any, Mapping]]
    row: Callable[[Any, dict], dict]
    selection: Selection
    evaluate: Callable[[Any, int], dict] | None = None
    last: Callable[[Any], Any] = lambda state: state
    best: Callable[[Any], Any] = lambda state: state
    restore: Callable[[Any], Any] = lambda tree: tree


@dataclass
class RunResult:
    """``state`` after the last epoch trained; ``history``: the metrics rows of every epoch
    of the run (resumed ones included); ``best``: the selection record; ``stopped``: early
    stopping ended the run."""

    state: Any
    history: list[dict]
    best: Best
    stopped: bool


def read_metrics(run_dir: str | Path, upto: int | None = None) -> list[dict]:
    """The rows of ``run_dir``'s ``metrics.jsonl`` (up to epoch ``upto``, when given)."""
    path = Path(run_dir) / METRICS_FILE
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] \
        if path.is_file() else []
    return [r for r in rows if upto is None or r["epoch"] <= upto]


def _write_metrics(path: Path, rows: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def _means(sums: dict[str, np.ndarray], total: float) -> dict[str, Any]:
    return {k: (v / total if v.ndim else float(v / total)) for k, v in sums.items()}


def train_epochs(run_dir: str | Path, spec: RunSpec, loop: Loop, init: Callable[[], Any],
                 abstract: Callable[[], Any], *, resume: bool = False,
                 stop_after: int | None = None, progress: bool = True,
                 on_epoch: Callable[[list[dict], Best], None] | None = None) -> RunResult:
    """Train ``loop`` in run folder ``run_dir``: epochs of ``loop.step`` over
    ``loop.batches``, a metrics row each (``epoch`` 1-based, ``loop.row``'s entries,
    ``train_time_s``, then ``loop.evaluate``'s and ``eval_time_s`` when it ran) appended to
    ``metrics.jsonl``, then the ``best`` checkpoint when the selection improved (or, at the
    last epoch, when no epoch has been best) and the ``last`` one; ``on_epoch(history, best)``
    after that.

    Args:
        init: the fresh training state; abstract: its structure (``jax.ShapeDtypeStruct``
            leaves are enough) as ``loop.last`` saves it, to restore into.
        resume: continue from the ``last`` checkpoint, which must have been written with
            ``spec.resolved`` (but for ``spec.ignore``); the result equals that of an
            uninterrupted run. Without a checkpoint it starts afresh.
        stop_after: stop after this many epochs of this call, as if killed after that
            epoch's checkpoint (tests, smoke runs).
        progress: a bar per epoch on stderr.

    Raises:
        DataError: a run folder that already holds checkpoints without ``resume``, or a
            checkpoint written with another configuration or format version (one line).
        FloatingPointError: a non-finite training metric.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    metrics_path = run_dir / METRICS_FILE
    ckpt = Checkpoints(run_dir, keep=spec.keep)
    best, start, stopped, history = Best(), 0, False, []
    try:
        if ckpt.latest() is not None and not resume:
            raise DataError("the run folder already holds checkpoints; resume it or use "
                            "another folder", run_dir)
        if resume and ckpt.latest() is not None:
            tree, meta = ckpt.restore("last", abstract(), spec.resolved, ignore=spec.ignore,
                                      defaults=spec.defaults, layout=spec.layout)
            state = loop.restore(tree)
            rec = meta["early_stopping"]
            best = Best(rec["best"], int(rec["bad_epochs"]), rec["best_epoch"])
            start, stopped = int(meta["position"]["epoch"]), bool(meta["stopped"])
            history = read_metrics(run_dir, start)
        else:
            state = init()
        _write_metrics(metrics_path, history)  # drops rows newer than the checkpoint
        # Restored arrays are committed to a device, fresh ones are not, and jit caches the
        # two apart: commit both so a resumed run reuses the uninterrupted run's executable.
        state = jax.device_put(state, jax.devices()[0])
        write_config(run_dir / CONFIG_FILE, spec.config, **spec.extras)
        for epoch in range(start, loop.epochs):
            if stopped or (stop_after is not None and epoch - start >= stop_after):
                break
            t0 = time.perf_counter()
            sums: dict[str, np.ndarray] = {}
            total = 0.0
            batches = loop.batches(epoch)
            try:
                for batch, weight in progress_bar(
                        batches, total=loop.steps, desc=f"epoch {epoch + 1}/{loop.epochs}",
                        enabled=progress, unit="step"):
                    state, metrics = loop.step(state, batch)
                    for k, v in jax.device_get(metrics).items():
                        sums[k] = sums.get(k, np.float64(0.0)) + np.asarray(v) * weight
                    total += weight
            finally:
                if hasattr(batches, "close"):
                    batches.close()
            means = _means(sums, max(total, 1.0))
            row: dict[str, Any] = {"epoch": epoch + 1, **loop.row(state, means),
                                   "train_time_s": time.perf_counter() - t0}
            if not all(np.all(np.isfinite(v)) for v in means.values()):
                raise FloatingPointError(f"non-finite training loss at epoch {epoch + 1}: "
                                         f"{row}")
            if loop.evaluate is not None:
                t1 = time.perf_counter()
                scores = loop.evaluate(state, epoch)
                if scores:
                    row.update(scores, eval_time_s=time.perf_counter() - t1)
            best, stopped = loop.selection.update(best, loop.selection.score(row), epoch + 1)
            improved = best.epoch == epoch + 1
            if best.epoch is None and epoch + 1 == loop.epochs:  # never scored: keep the last
                best, improved = best._replace(epoch=epoch + 1), True
            history.append(row)
            with metrics_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
            meta = {"epoch": epoch + 1, "position": {"epoch": epoch + 1, "batch": 0},
                    "early_stopping": {"best": best.score, "bad_epochs": best.bad_epochs,
                                       "best_epoch": best.epoch},
                    "stopped": stopped, "config": dict(spec.resolved), **spec.meta}
            if improved:
                ckpt.save("best", epoch + 1, loop.best(state), meta)
            ckpt.save("last", epoch + 1, loop.last(state), meta)
            if on_epoch is not None:
                on_epoch(history, best)
    finally:
        ckpt.close()
    return RunResult(state=state, history=history, best=best, stopped=stopped)
