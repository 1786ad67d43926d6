"""Shared parts of the calibrator experiments (``calib_protocols.py``, ``calib_ablation.py``).

- The two configurations: **budget** (:data:`BUDGET_SETTINGS`, a model and windows small
  enough for minutes on 2 CPU cores) and **paper** (Table 2 of Avola et al. 2023, which are
  the package defaults), both as ``uavcal calib train --set`` strings.
- Run settings, trials and statistics come from :mod:`uavcal_jax.calib.protocols`, as for
  ``uavcal calib train``.
- The simulated sets (:func:`uavcal_jax.calib.sim_sets.simulated_set`, rendered once into the
  cache) and their windows, optionally with every ``k``-th frame kept (:func:`decimate`).
- :func:`train_jobs`: a time budget spread over many fits as **one common epoch count**: every
  fit runs two epochs (the second times an epoch without its compile), then rounds raise all
  unfinished fits to a common target as far as the time left allows, resuming them from their
  checkpoints (``fit(resume=True, stop_after=n)``; a resumed run equals an uninterrupted one).
  Fits of one table thus train equally long (or stop early by the paper's patience), and the
  time a fit frees by stopping early goes to the others.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from uavcal_jax.calib.config import CalibConfig, TrainConfig
from uavcal_jax.calib.data import (
    Windows,
    load_windows,
)
from uavcal_jax.calib.loop import LoopConfig, fit
from uavcal_jax.calib.sim_sets import SimSetConfig, sequence_configs, simulated_set
from uavcal_jax.data.windows import WindowConfig, WindowSet

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CACHE = ROOT / "experiments" / "out" / "calib_cache"
#: Budget mode (``--set`` strings): 160x96 gray frames in 32x32 patches (5x3 patches), d 64,
#: 4 heads, 2 layers, 2 s windows, batch 16 and a learning rate of 1e-3 (the paper's 1e-5
#: needs its 100 epochs); everything else as the paper. Each script adds its window stride
#: and frame step (the sizes that set its cost).
BUDGET_SETTINGS = ("model.d_model=64", "model.heads=4", "model.layers=2", "model.patch=32,32",
                   "train.learning_rate=1e-3", "window.size=160x96", "window.duration=2")
#: Paper mode: Table 2 is the package default (d 256, 8 heads, 2 layers, patch 64x64, 320x180,
#: 10 s windows, 1 s stride, batch 16, lr 1e-5, 100 epochs, patience 3).
PAPER_SETTINGS: tuple[str, ...] = ()


def add_common_arguments(ap: argparse.ArgumentParser, out_default: Path,
                         budget_frame_step: int) -> None:
    """The options both scripts share (``budget_frame_step``: the budget mode's default
    ``--frame-step``; the paper mode's is 1)."""
    from uavcal_jax.argtypes import positive, positive_int

    ap.add_argument("--budget", type=positive, default=20.0, metavar="MINUTES",
                    help="wall-clock budget of the whole script; the epoch count is chosen "
                         "to fill it (ignored with --paper) [default: %(default)s]")
    ap.add_argument("--paper", action="store_true",
                    help="the paper's configuration (Table 2) and its full epochs with early "
                         "stopping, no time limit (days on a CPU)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                    help="simulated-set cache [default: %(default)s]")
    ap.add_argument("--out", type=Path, default=out_default,
                    help="output folder [default: %(default)s]")
    ap.add_argument("--sequences", type=_names, default=None, metavar="A,B,...",
                    help="keep only these simulated sequences (trajectory names, e.g. "
                         "MH_01_easy,V1_01_easy,indoor_45_2) [default: all]")
    ap.add_argument("--max-duration", type=positive, default=None, metavar="S",
                    help="cap every simulated sequence at S seconds (a separate cache entry; "
                         "for smoke runs) [default: whole trajectories]")
    ap.add_argument("--frame-step", type=positive_int, default=None, metavar="K",
                    help="keep every K-th frame slot of each window (and its IMU sample): "
                         f"T / K frames per window at 20 / K Hz [default: {budget_frame_step}, "
                         "with --paper 1]")
    ap.set_defaults(budget_frame_step=budget_frame_step)
    ap.add_argument("--max-epochs", type=positive_int, default=None, metavar="N",
                    help=f"most epochs of a fit [default: train.epochs, {TrainConfig.epochs}]")
    ap.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                    help="more `uavcal calib train --set` fields, applied after the mode's")
    ap.add_argument("--quiet", action="store_true", help="no progress bars or log lines")


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip())


def log(quiet: bool, *parts) -> None:
    """A progress line on stderr (stdout ends with the one JSON line)."""
    if not quiet:
        print(*parts, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- configuration


def mode_settings(args: argparse.Namespace, budget_extra: Sequence[str] = ()) -> list[str]:
    """The mode's ``--set`` strings (budget: :data:`BUDGET_SETTINGS` and the script's
    ``budget_extra``), then the user's ``--set``; fills in ``args.frame_step``."""
    if args.frame_step is None:
        args.frame_step = 1 if args.paper else args.budget_frame_step
    mode = PAPER_SETTINGS if args.paper else (*BUDGET_SETTINGS, *budget_extra)
    return [*mode, *args.set]


def describe(calib: CalibConfig, window: WindowConfig, frames_per_window: int | None,
             frame_step: int) -> str:
    """One line naming the model, windows and optimiser of a run (the tables' header)."""
    m, t = calib.model, calib.train
    rate = f", every {frame_step}th frame" if frame_step > 1 else ""
    frames = "?" if frames_per_window is None else frames_per_window
    return (f"frames {window.size[0]}x{window.size[1]} {window.color}, patch "
            f"{m.patch[0]}x{m.patch[1]}, d {m.d_model}, {m.heads} heads, {m.layers} layers, "
            f"dropout {m.dropout:g}, {'video + IMU' if m.use_video else 'IMU only'}; "
            f"{window.duration:g} s windows ({frames} frames{rate}) every "
            f"{window.stride:g} s; batch {t.batch_size}, AdamW lr {t.learning_rate:g}, "
            f"patience {t.patience}; loss sign term {calib.loss.sign_term!r}; injection "
            f"{calib.injection.protocol!r} (n_m {calib.injection.noise_multiplier:g})")


# ----------------------------------------------------------------------------- data


def family_names(family: str) -> list[str]:
    """Every sequence name of a simulated family."""
    return [name for name, _ in sequence_configs(SimSetConfig(family=family))]


def pick_sequences(family: str, wanted: Sequence[str] | None,
                   only: Sequence[str] | None = None) -> list[str]:
    """The family's names kept by ``--sequences`` (``wanted``) and ``only``, in set order."""
    names = family_names(family)
    if only is not None:
        names = [n for n in names if n in set(only)]
    return names if wanted is None else [n for n in names if n in set(wanted)]


def render(family: str, names: Sequence[str], max_duration: float | None, cache: Path,
           quiet: bool) -> list[Path]:
    """The folders of ``names`` of ``family``, rendered into ``cache`` if missing."""
    cfg = SimSetConfig(family=family, max_duration=max_duration, sequences=tuple(names))
    return simulated_set(cfg, cache, progress=not quiet)


def decimate(ws: WindowSet, step: int) -> WindowSet:
    """``ws`` with every ``step``-th frame slot of each window kept (``T -> ceil(T / step)``
    slots, frames and their nearest IMU samples at ``rate / step``); the full-rate IMU
    (``imu_range``, used by the least-squares baseline) and the shared frames stay."""
    if step == 1:
        return ws
    index = np.ascontiguousarray(ws.frame_index[:, ::step])
    return dataclasses.replace(ws, frame_index=index,
                               frame_mask=np.ascontiguousarray(ws.frame_mask[:, ::step]),
                               meta={**ws.meta, "frame_step": step,
                                     "frames_per_window": index.shape[1]})


def window_subset(ws: WindowSet, indices) -> WindowSet:
    """The windows ``indices`` of ``ws`` as a WindowSet of their own (frames shared)."""
    idx = np.asarray(indices, np.int64)
    return dataclasses.replace(ws, start_ns=ws.start_ns[idx], frame_index=ws.frame_index[idx],
                               frame_mask=ws.frame_mask[idx], imu_range=ws.imu_range[idx])


def load_parts(folders: Sequence[Path], window: WindowConfig, frame_step: int
               ) -> list[Windows]:
    """Every window of ``folders`` (:func:`uavcal_jax.calib.data.load_windows`), decimated."""
    return [p._replace(windows=decimate(p.windows, frame_step))
            for p in load_windows(folders, window)]


# ----------------------------------------------------------------------------- budget


class Budget:
    """Wall-clock budget from construction; ``minutes=None``: unlimited."""

    def __init__(self, minutes: float | None):
        self.start = time.perf_counter()
        self.seconds = None if minutes is None else 60.0 * minutes

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float:
        return math.inf if self.seconds is None else self.seconds - self.elapsed()


@dataclass
class Job:
    """One fit: its configuration, data (``data()`` returns ``(train, val)``, so a caller may
    load lazily) and run folder; the rest is filled in by :func:`train_jobs`."""

    name: str
    config: CalibConfig
    loop: LoopConfig
    data: Callable[[], tuple[list[Windows], list[Windows]]]
    run_dir: Path
    epochs: int = 0
    stopped: bool = False
    epoch_s: float = math.nan  # seconds per epoch, from the last call (the first: with compile)
    first_s: float = math.nan  # wall seconds of the first call (compile, init, one epoch)
    train_s: float = 0.0
    calls: int = 0
    releases: int = 0  # times the compiled functions were dropped after this job's calls
    summary: dict = field(default_factory=dict)

    @property
    def max_epochs(self) -> int:
        return self.config.train.epochs


def release_if_crowded() -> bool:
    """Drop JAX's compiled functions when this process's memory mappings pass half of
    ``vm.max_map_count``; returns whether it did.

    Every CPU executable holds LLVM-JIT mappings (a grid point's train, eval and init steps:
    about 2,000), so a few dozen configurations exhaust the default limit of 65,530 and the
    next compile fails ("LLVM compilation error: Cannot allocate memory", then a crash).
    :func:`jax.clear_caches` frees them; the persistent compilation cache turns the recompile
    of a resumed fit into a load (its retrace remains).
    """
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps") as f:
            used = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if used <= limit // 2:
        return False
    jax.clear_caches()
    gc.collect()
    return True


def _release(job: Job, quiet: bool) -> None:
    if release_if_crowded():
        job.releases += 1
        log(quiet, "  (compiled functions released: memory mappings past half the limit)")


def _advance(job: Job, epochs: int, quiet: bool):
    train, val = job.data()
    t0 = time.perf_counter()
    res = fit(job.config, train, val, job.run_dir, resume=job.calls > 0, progress=not quiet,
              loop=job.loop, stop_after=epochs)
    dt = time.perf_counter() - t0
    ran = res.summary["epochs"] - job.epochs
    if job.calls == 0:
        job.first_s = dt
    job.epoch_s = dt / max(ran, 1)
    job.epochs, job.stopped = res.summary["epochs"], res.summary["stopped_early"]
    job.train_s += dt
    job.calls += 1
    job.summary = res.summary
    b = res.summary["best"]
    log(quiet, f"  {job.name}: {job.epochs} epochs ({dt:.1f} s), best {res.summary['best_epoch']}"
               f": val offset RMSE {b.get('val_offset_rmse', math.nan):.4f}, sign F1 "
               f"{b.get('val_sign_f1', math.nan):.3f}")
    return res


def train_jobs(jobs: Sequence[Job], budget: Budget, *, reserve_s: float = 0.0,
               quiet: bool = False, after_first: Callable | None = None) -> dict:
    """Train every job; returns the schedule's record (JSON-ready).

    Unlimited budget: each job runs to its ``train.epochs`` (or its early stop) in one call.
    Otherwise each job first runs two epochs in two calls while its compiled steps are in
    memory (the second call times an epoch without the compile), then rounds raise every
    unfinished job to a common target ``E``: ``E`` grows by ``floor((time left - reserve_s -
    re-entry) / sum of their epoch times)`` per round until no further epoch fits (re-entry:
    each job's first-call overhead, counted once compiled functions have been released and
    must be reloaded). Every job runs its first two epochs even past the budget (recorded).
    ``after_first(job, fit_result)`` runs after each job's first call (its state in memory).
    """
    unlimited = budget.seconds is None
    for i, job in enumerate(jobs):
        res = _advance(job, job.max_epochs if unlimited else 1, quiet)
        if after_first is not None:
            after_first(job, res)
        del res
        if not unlimited and not job.stopped and job.epochs < job.max_epochs:
            _advance(job, 1, quiet)
        _release(job, quiet)
        if i == 0 and not unlimited and len(jobs) > 1:
            projected = budget.elapsed() + (len(jobs) - 1) * job.first_s
            if projected > budget.seconds:
                log(quiet, f"warning: the first epoch of the {len(jobs)} fits (with their "
                           f"compiles) will take about {projected / 60:.1f} min, past the "
                           f"{budget.seconds / 60:g} min budget: fewer sequences or grids, a "
                           "longer stride or --frame-step fit it")
    target, rounds = (None, 0) if unlimited else (max(j.epochs for j in jobs), 0)
    while not unlimited:
        active = [j for j in jobs if not j.stopped and j.epochs < j.max_epochs]
        if not active:
            break
        released = any(j.releases for j in jobs)
        reentry = sum(max(0.0, j.first_s - j.epoch_s) for j in active) if released else 0.0
        add = int((budget.left() - reserve_s - reentry) // sum(j.epoch_s for j in active))
        if add < 1:
            break
        target += add
        rounds += 1
        log(quiet, f"round {rounds}: {len(active)} fits to {target} epochs "
                   f"({budget.left() / 60:.1f} min left)")
        for job in active:
            _advance(job, min(target, job.max_epochs) - job.epochs, quiet)
            _release(job, quiet)
    return {"target_epochs": target, "rounds": rounds,
            "epochs": {j.name: j.epochs for j in jobs},
            "stopped_early": {j.name: j.stopped for j in jobs},
            "first_call_s": {j.name: round(j.first_s, 2) for j in jobs},
            "epoch_s": {j.name: round(j.epoch_s, 3) for j in jobs},
            "train_s": round(sum(j.train_s for j in jobs), 1),
            "compile_releases": sum(j.releases for j in jobs)}


def best_row(job: Job) -> dict:
    """The job's ``metrics.jsonl`` row of its best epoch (``val_metrics``: per seed)."""
    best = job.summary["best_epoch"]
    for line in (job.run_dir / "metrics.jsonl").read_text().splitlines():
        if line.strip() and json.loads(line)["epoch"] == best:
            return json.loads(line)
    raise ValueError(f"{job.run_dir}: no metrics row of epoch {best}")


def budget_record(budget: Budget, paper: bool, minutes: float) -> dict:
    """What the results record of the budget."""
    wall = budget.elapsed()
    return {"mode": "paper" if paper else "budget", "budget_min": None if paper else minutes,
            "wall_s": round(wall, 1),
            "over_budget_s": None if paper else round(max(0.0, wall - 60.0 * minutes), 1)}


def fmt_mean_std(stat: dict | None, scale: float = 1.0, digits: int = 3) -> str:
    """``"m ± s"`` of a ``{"mean", "std"}`` dict (``"-"`` when missing)."""
    if not stat or stat.get("mean") is None or not np.isfinite(stat["mean"]):
        return "-"
    return f"{stat['mean'] * scale:.{digits}f} ± {stat['std'] * scale:.{digits}f}"
