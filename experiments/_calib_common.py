"""Shared parts of the calibrator experiments (``calib_protocols.py``, ``calib_ablation.py``).

- The two modes, both presets of :data:`uavcal_jax.calib.protocols.PRESETS` (what ``uavcal
  calib train --preset`` reads): **budget** = ``small`` (160x96 frames in 32x32 patches at
  10 Hz, d 64, pre-norm, AdamW 1e-3, the loss in each channel's offset units, patience 10),
  with a window every 10 s (the preset's window length: non-overlapping, :func:`resolve`);
  **paper** (``--paper``) = ``paper`` (Table 2 of Avola et al. 2023, the package defaults,
  1 s stride). ``--set`` strings apply last, in either mode.
- Run settings, trials and statistics come from :mod:`uavcal_jax.calib.protocols`, as for
  ``uavcal calib train``.
- The simulated sets (:func:`uavcal_jax.calib.sim_sets.simulated_set`, rendered once into the
  cache) and their windows.
- :func:`train_jobs`: a time budget spread over many fits as **one common epoch count**: every
  fit runs two epochs (the second times an epoch without its compile), then rounds raise all
  unfinished fits to a common target as far as the time left allows, resuming them from their
  checkpoints (``fit(resume=True, stop_after=n)``; a resumed run equals an uninterrupted one).
  Fits of one table thus train equally long (or stop early by their configuration's patience
  on the training loss, the paper's criterion), and the time a fit frees by stopping early
  goes to the others. Fits validate nothing per epoch (unless ``loop.monitor=val``): the time
  left for the final evaluations is set aside instead, and :func:`evaluate_best` evaluates
  each fit's best checkpoint once, with ``loop.val_offsets`` offsets.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from uavcal_jax.calib.config import CalibConfig, TrainConfig
from uavcal_jax.calib.data import Windows
from uavcal_jax.calib.loop import LoopConfig, evaluate, fit, restore_run
from uavcal_jax.calib.protocols import resolve_configs
from uavcal_jax.calib.sim_sets import SimSetConfig, sequence_configs, simulated_set
from uavcal_jax.data.windows import WindowConfig, WindowSet

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CACHE = ROOT / "experiments" / "out" / "calib_cache"
#: The presets (:data:`uavcal_jax.calib.protocols.PRESETS`) of the two modes.
BUDGET_PRESET, PAPER_PRESET = "small", "paper"
#: Forward pass over a window / one training step's work on it (forward, backward, AdamW),
#: rounded up from the video model's 0.34 on 2 cores: sizes the time set aside for the final
#: evaluations.
FORWARD_SHARE = 0.5
#: Seconds per final evaluation besides its forward passes (restore, compile lookups).
EVAL_OVERHEAD_S = 5.0


def add_common_arguments(ap: argparse.ArgumentParser, out_default: Path) -> None:
    """The options both scripts share."""
    from uavcal_jax.argtypes import positive, positive_int

    ap.add_argument("--budget", type=positive, default=20.0, metavar="MINUTES",
                    help="wall-clock budget of the whole script; the common epoch count is "
                         "chosen to fill it (ignored with --paper) [default: %(default)s]")
    ap.add_argument("--paper", action="store_true",
                    help=f"the {PAPER_PRESET!r} preset (Table 2) and its full epochs with "
                         "early stopping, no time limit (days on a CPU) [default: the "
                         f"{BUDGET_PRESET!r} preset, a window every window length]")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                    help="simulated-set cache [default: %(default)s]")
    ap.add_argument("--out", type=Path, default=out_default,
                    help="output folder [default: %(default)s]")
    ap.add_argument("--sequences", type=names_list, default=None, metavar="A,B,...",
                    help="keep only these simulated sequences (trajectory names, e.g. "
                         "MH_01_easy,V1_01_easy,indoor_45_2) [default: all]")
    ap.add_argument("--max-duration", type=positive, default=None, metavar="S",
                    help="cap every simulated sequence at S seconds (a separate cache entry; "
                         "for smoke runs) [default: whole trajectories]")
    ap.add_argument("--max-epochs", type=positive_int, default=None, metavar="N",
                    help=f"most epochs of a fit [default: train.epochs, {TrainConfig.epochs}]")
    ap.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                    help="more `uavcal calib train --set` fields (window.*, loop.* included), "
                         "applied after the mode's preset, e.g. window.frame_step=4")
    ap.add_argument("--quiet", action="store_true", help="no progress bars or log lines")


def names_list(text: str) -> tuple[str, ...]:
    """``"A,B"`` -> ``("A", "B")`` (an argparse type)."""
    return tuple(n.strip() for n in text.split(",") if n.strip())


def log(quiet: bool, *parts) -> None:
    """A progress line on stderr (stdout ends with the one JSON line)."""
    if not quiet:
        print(*parts, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- configuration


def preset(args: argparse.Namespace) -> str:
    """The mode's preset name."""
    return PAPER_PRESET if args.paper else BUDGET_PRESET


def resolve(args: argparse.Namespace, sets: Sequence[str] = (), **kwargs
            ) -> tuple[CalibConfig, LoopConfig, WindowConfig]:
    """:func:`~uavcal_jax.calib.protocols.resolve_configs` of the mode: its preset, the
    arguments ``kwargs``, the script's ``sets``, then ``--set``. Budget mode cuts a window
    every ``window.duration`` seconds of the mode's own configuration (preset and ``--set``:
    10 s, non-overlapping windows, the same data per epoch at a tenth of the paper's 1 s
    stride's cost) unless a setting gives the stride; a script's ``sets`` that change the
    window length keep that stride, as the paper keeps its 1 s, so every window length has
    as many windows, and as many steps per epoch."""
    both = [*sets, *args.set]
    calib, loop, window = resolve_configs(both, preset=preset(args), **kwargs)
    if not args.paper and not any(s.split("=")[0].strip() == "window.stride" for s in both):
        _, _, mode_window = resolve_configs(args.set, preset=preset(args))
        window = dataclasses.replace(window, stride=mode_window.duration)
    return calib, loop, window


def describe(calib: CalibConfig, window: WindowConfig, frames_per_window: int | None) -> str:
    """One line naming the model, windows and optimiser of a run (the tables' header)."""
    m, t = calib.model, calib.train
    frames = "?" if frames_per_window is None else (
        f"{frames_per_window} frames at {frames_per_window / window.duration:g} Hz")
    return (f"frames {window.size[0]}x{window.size[1]} {window.color}, patch "
            f"{m.patch[0]}x{m.patch[1]}, d {m.d_model}, {m.heads} heads, {m.layers} "
            f"{'pre' if m.norm_first else 'post'}-norm layers, dropout {m.dropout:g}, "
            f"{'video + IMU' if m.use_video else 'IMU only'}, "
            f"{'standardised' if m.standardize else 'raw SI'} IMU in and offsets out; "
            f"{window.duration:g} s windows ({frames}) every "
            f"{window.stride:g} s; batch {t.batch_size}, AdamW lr {t.learning_rate:g}, "
            f"patience {t.patience}; loss sign term {calib.loss.sign_term!r}, "
            f"{calib.loss.units} units; injection {calib.injection.protocol!r} "
            f"(n_m {calib.injection.noise_multiplier:g})")


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


def window_subset(ws: WindowSet, indices) -> WindowSet:
    """The windows ``indices`` of ``ws`` as a WindowSet of their own (frames shared)."""
    idx = np.asarray(indices, np.int64)
    return dataclasses.replace(ws, start_ns=ws.start_ns[idx], frame_index=ws.frame_index[idx],
                               frame_mask=ws.frame_mask[idx], imu_range=ws.imu_range[idx])


def count(parts: Sequence[Windows]) -> int:
    """Windows in ``parts``."""
    return int(sum(len(p.indices) for p in parts))


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
    job.eval_share = count(val) * job.loop.val_offsets / max(count(train), 1)
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
    log(quiet, f"  {job.name}: {job.epochs} epochs ({dt:.1f} s), best epoch "
               f"{res.summary['best_epoch']}, training loss "
               f"{res.summary['best'].get('loss', math.nan):.4f}")
    return res


def train_jobs(jobs: Sequence[Job], budget: Budget, *, reserve_s: float = 0.0,
               quiet: bool = False, after_first: Callable | None = None) -> dict:
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
                log(quiet, f"warning: the first two epochs of the {len(jobs)} fits will end "
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


def budget_record(budget: Budget, paper: bool, minutes: float) -> dict:
    """What the results record of the budget."""
    wall = budget.elapsed()
    return {"mode": "paper" if paper else "budget", "budget_min": None if paper else minutes,
            "wall_s": round(wall, 1),
            "over_budget_s": None if paper else round(max(0.0, wall - 60.0 * minutes), 1)}


def mode_line(rec_budget: dict, schedule: dict, max_epochs: int, what: str) -> str:
    """The tables' first line: the mode, budget, minutes taken and epochs of ``what``."""
    took = f"took {rec_budget['wall_s'] / 60:.1f} min"
    if rec_budget["mode"] == "paper":
        return (f"paper mode (preset {PAPER_PRESET!r}: Table 2, at most {max_epochs} epochs, "
                f"early stopping on the training loss); {took}")
    return (f"budget mode (preset {BUDGET_PRESET!r}, stride = its window length): "
            f"{rec_budget['budget_min']:g} min for the whole script ({took}); {what} "
            f"{schedule['target_epochs']} epochs (two first, then a common count that fills "
            "the time left; fewer where early stopping ended a fit), best epoch by training "
            "loss")


def fmt_mean_std(stat: dict | None, scale: float = 1.0, digits: int = 3) -> str:
    """``"m ± s"`` of a ``{"mean", "std"}`` dict (``"-"`` when missing)."""
    if not stat or stat.get("mean") is None or not np.isfinite(stat["mean"]):
        return "-"
    return f"{stat['mean'] * scale:.{digits}f} ± {stat['std'] * scale:.{digits}f}"
