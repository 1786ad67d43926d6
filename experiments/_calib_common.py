"""Shared parts of the calibrator experiments (``calib_protocols.py``, ``calib_ablation.py``).

- The two modes, both presets of :data:`uavcal_jax.calib.presets.PRESETS` (what ``uavcal
  calib train --preset`` reads): **budget** = ``small`` (160x96 frames in 32x32 patches at
  10 Hz, d 64, pre-norm, AdamW 1e-3, the loss in each channel's offset units, patience 10),
  with a window every 10 s (the preset's window length: non-overlapping,
  :func:`uavcal_jax.calib.presets.budget_stride`);
  **paper** (``--paper``) = ``paper`` (Table 2 of Avola et al. 2023, the package defaults,
  1 s stride). ``--set`` strings apply last, in either mode.
- Run settings come from :mod:`uavcal_jax.calib.presets`, trials, their run folders and
  statistics from :mod:`uavcal_jax.calib.trials`, as for ``uavcal calib train``; the budget is
  spread over the fits by :mod:`uavcal_jax.calib.schedule` (one common epoch count for every
  fit of a table).
- The simulated sets (:func:`uavcal_jax.sim.training_sets.simulated_set`, rendered once into
  the cache; their trajectories under :data:`SHARED_DATA`).
- The options both scripts share, and the lines and cells of their tables.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from _docs import add_write_docs  # the script's folder is first on sys.path

from uavcal_jax.calib.config import CalibConfig, LoopConfig, TrainConfig
from uavcal_jax.calib.presets import budget_stride, resolve_configs
from uavcal_jax.calib.schedule import Budget
from uavcal_jax.data.windows import WindowConfig
from uavcal_jax.sim.training_sets import SimSetConfig, sequence_configs, simulated_set

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CACHE = ROOT / "experiments" / "out" / "calib_cache"
#: The shared data beside the checkout (the simulated sets' trajectories).
SHARED_DATA = ROOT.parent / "shared" / "data"
#: The presets (:data:`uavcal_jax.calib.presets.PRESETS`) of the two modes.
BUDGET_PRESET, PAPER_PRESET = "small", "paper"


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
    add_write_docs(ap)


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
    """:func:`~uavcal_jax.calib.presets.resolve_configs` of the mode: its preset, the
    arguments ``kwargs``, the script's ``sets``, then ``--set``; in budget mode with
    :func:`~uavcal_jax.calib.presets.budget_stride` (a window every window length of the
    mode's own configuration, unless a setting gives the stride)."""
    both = [*sets, *args.set]
    run = resolve_configs(both, preset=preset(args), **kwargs)
    if not args.paper:
        run = budget_stride(run, resolve_configs(args.set, preset=preset(args)), both)
    return run.calib, run.loop, run.window


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
    return [name for name, _ in sequence_configs(SimSetConfig(family=family), SHARED_DATA)]


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
    return simulated_set(cfg, cache, data_root=SHARED_DATA, progress=not quiet)


# ----------------------------------------------------------------------------- records, tables


def budget_record(budget: Budget, paper: bool) -> dict:
    """What the results record of the budget: the mode and :meth:`Budget.record`."""
    return {"mode": "paper" if paper else "budget", **budget.record()}


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
