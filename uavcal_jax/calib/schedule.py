"""A wall-clock budget spread over many calibrator fits as **one common epoch count** (the
experiments' tables: every fit of a table trains equally long).

:func:`train_jobs`: every fit (:class:`Job`) runs two epochs (the second times an epoch
without its compile), then rounds raise all unfinished fits to a common target as far as the
time left (:class:`Budget`) allows, resuming them from their checkpoints
(``fit(resume=True, stop_after=n)``; a resumed run equals an uninterrupted one). Fits stop
early by their configuration's patience on the training loss (the paper's criterion), and
the time a fit frees by stopping early goes to the others. Fits validate nothing per epoch
(unless ``loop.monitor=val``): the time of the final evaluations is set aside instead, and
:func:`evaluate_best` evaluates each fit's best checkpoint once, with ``loop.val_offsets``
offsets. After each job's calls the compiled functions are dropped if the process's memory
mappings crowd (:func:`uavcal_jax.xla_cache.release_if_crowded`).

Progress lines go to stderr unless ``quiet``.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uavcal_jax.calib.config import CalibConfig, LoopConfig
from uavcal_jax.calib.data import Windows, count_windows
from uavcal_jax.calib.loop import FitResult, evaluate, fit, restore_run
from uavcal_jax.xla_cache import release_if_crowded

__all__ = ["EVAL_OVERHEAD_S", "FORWARD_SHARE", "Budget", "Job", "evaluate_best", "train_jobs"]

#: Forward pass over a window / one training step's work on it (forward, backward, AdamW),
#: rounded up from the video model's 0.34 on 2 cores: sizes the time set aside for the final
#: evaluations.
FORWARD_SHARE = 0.5
#: Seconds per final evaluation besides its forward passes (restore, compile lookups).
EVAL_OVERHEAD_S = 5.0


def _note(quiet: bool, *parts) -> None:
    if not quiet:
        print(*parts, file=sys.stderr, flush=True)


class Budget:
    """Wall-clock budget from construction; ``minutes=None``: unlimited."""

    def __init__(self, minutes: float | None):
        self.start = time.perf_counter()
        self.minutes = minutes
        self.seconds = None if minutes is None else 60.0 * minutes

    def elapsed(self) -> float:
        """Seconds since construction."""
        return time.perf_counter() - self.start

    def left(self) -> float:
        """Seconds left (``inf`` when unlimited; negative past the budget)."""
        return math.inf if self.seconds is None else self.seconds - self.elapsed()

    def record(self) -> dict:
        """JSON-ready: ``budget_min`` (``None``: unlimited), ``wall_s`` so far and
        ``over_budget_s`` (``None``: unlimited)."""
        wall = self.elapsed()
        return {"budget_min": self.minutes, "wall_s": round(wall, 1),
                "over_budget_s": None if self.seconds is None else
                round(max(0.0, wall - self.seconds), 1)}


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
    eval_share: float = 0.0  # validation windows x offsets / training windows
    calls: int = 0
    releases: int = 0  # times the compiled functions were dropped after this job's calls
    summary: dict = field(default_factory=dict)

    @property
    def max_epochs(self) -> int:
        return self.config.train.epochs

    def eval_estimate_s(self) -> float:
        """The expected time of this job's final evaluation (:func:`evaluate_best`)."""
        epoch = 0.0 if math.isnan(self.epoch_s) else self.epoch_s
        return FORWARD_SHARE * epoch * self.eval_share + EVAL_OVERHEAD_S


def _release(job: Job, quiet: bool) -> None:
    if release_if_crowded():
        job.releases += 1
        _note(quiet, "  (compiled functions released: memory mappings past half the limit)")


def _advance(job: Job, epochs: int, quiet: bool) -> FitResult:
    """Train ``job`` ``epochs`` more epochs (resuming after its first call)."""
    train, val = job.data()
    job.eval_share = count_windows(val) * job.loop.val_offsets / max(count_windows(train), 1)
    t0 = time.perf_counter()
    res = fit(job.config, train, val if job.loop.monitor == "val" else None, job.run_dir,
              resume=job.calls > 0, progress=not quiet, loop=job.loop, stop_after=epochs)
    dt = time.perf_counter() - t0
    ran = res.summary["epochs"] - job.epochs
    if job.calls == 0:
        job.first_s = dt
    job.epoch_s = dt / max(ran, 1)
    job.epochs, job.stopped = res.summary["epochs"], res.summary["stopped_early"]
    job.train_s += dt
    job.calls += 1
    job.summary = res.summary
    _note(quiet, f"  {job.name}: {job.epochs} epochs ({dt:.1f} s), best epoch "
                 f"{res.summary['best_epoch']}, training loss "
                 f"{res.summary['best'].get('loss', math.nan):.4f}")
    return res


def train_jobs(jobs: Sequence[Job], budget: Budget, *, reserve_s: float = 0.0,
               quiet: bool = False,
               after_first: Callable[[Job, FitResult], None] | None = None) -> dict:
    """Train every job; returns the schedule's record (JSON-ready).

    Unlimited budget: each job runs to its ``train.epochs`` (or its early stop) in one call.
    Otherwise each job first runs two epochs in two calls while its compiled steps are in
    memory (the second call times an epoch without the compile), then rounds raise every
    unfinished job to a common target ``E``: ``E`` grows by ``floor((time left - set aside)
    / sum of their epoch times)`` per round until no further epoch fits. Set aside:
    ``reserve_s`` (the caller's work after training), every job's final evaluation
    (:meth:`Job.eval_estimate_s`) and, once compiled functions have been released and must
    be reloaded, each job's first-call overhead. Every job runs its first two epochs even
    past the budget (recorded). ``after_first(job, fit_result)`` runs after each job's first
    call (its state in memory); the time it takes comes out of the budget before the rounds.
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
            projected = budget.elapsed() + (len(jobs) - 1) * 2 * job.epoch_s
            if projected > budget.seconds:
                _note(quiet, f"warning: the first two epochs of the {len(jobs)} fits will end "
                             f"about {projected / 60:.1f} min into the run (more with new "
                             f"compiles), past the {budget.seconds / 60:g} min budget: fewer "
                             "sequences, trials or grid points, or a larger window.frame_step "
                             "fit it")
    target, rounds = (None, 0) if unlimited else (max(j.epochs for j in jobs), 0)
    while not unlimited:
        active = [j for j in jobs if not j.stopped and j.epochs < j.max_epochs]
        if not active:
            break
        released = any(j.releases for j in jobs)
        reentry = sum(max(0.0, j.first_s - j.epoch_s) for j in active) if released else 0.0
        aside = reserve_s + reentry + sum(j.eval_estimate_s() for j in jobs)
        add = int((budget.left() - aside) // sum(j.epoch_s for j in active))
        if add < 1:
            break
        target += add
        rounds += 1
        _note(quiet, f"round {rounds}: {len(active)} fits to {target} epochs "
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


def evaluate_best(job: Job, offsets: np.ndarray | None = None, quiet: bool = False):
    """``(state, seeds, result)``: the job's best checkpoint restored and evaluated on its
    validation windows by :func:`uavcal_jax.calib.loop.evaluate`, once per offset
    (``offsets (K, C)``; default the run's ``loop.val_offsets`` draws)."""
    _, val = job.data()
    state, seeds = restore_run(job.run_dir, val)
    result = evaluate(state, val, seeds, offsets=offsets, draws=job.loop.val_offsets,
                      show=not quiet)
    _release(job, quiet)
    return state, seeds, result
