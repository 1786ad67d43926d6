"""The calibrator's ablations: the grids of Table 1 (window length) and Table 5 (dropout, hidden
size, heads, layers, noise multiplier, patch size) of Avola et al. (Sensors 2023), the sign-loss
surrogate against the exact sign term, and the optimisation choices of the ``small`` preset
(standardised IMU and offsets, pre-norm layers, the loss in offset units, the learning
rate), with Figure 3's metric-against-value plots.

Every grid point is one ``uavcal calib train`` fit: the mode's configuration with one field
changed, ``K`` seeds vmapped (``--seeds``, ``train.seeds``), trained on the simulated set minus
a fixed set of held-out sequences (``--val-sequences``; the paper's fixed 80/20 split is over
windows, but overlapping windows share most of their frames, so a split over windows validates
on frames it trained on), best epoch by training loss (the paper's early stopping), then
evaluated on every window of the held-out sequences once per offset, with the ``K =
loop.val_offsets`` offsets the point's protocol draws (:func:`uavcal_jax.calib.loop.evaluate`;
points that share the protocol and training windows share the offsets). Reported per grid
point: mean ± std over the seeds of the validation offset RMSE and sign F1, beside two
baselines on the same windows and offsets: the mean offset and the window mean (each window's
mean IMU sample minus the training set's, no learning).

Grids (``--grids``; the value of the mode's configuration is starred in the table):

============  ================================  ====================  ======================
grid          field                             budget values         full grid
============  ================================  ====================  ======================
window        ``window.duration`` (s)           2 10                  2 4 6 8 10
dropout       ``model.dropout``                 .01 .2                0 .01 .05 .1 .2
hidden        ``model.d_model``                 32 64                 32 64 128 256 512
heads         ``model.heads``                   1 4                   1 2 4 8 16
layers        ``model.layers``                  1 2                   1 2 3 4 5 6 7
noise         ``injection.noise_multiplier``    1 2                   1 2 3 4
patch         ``model.patch`` (square, px)      32 64                 32 64 96 128
sign          ``loss.sign_term``                sign tanh             sign tanh
standardize   ``model.standardize``             false true            false true
norm_first    ``model.norm_first``              false true            false true
units         ``loss.units``                    si standardized       si standardized
lr            ``train.learning_rate``           1e-5 1e-4 1e-3        1e-5 1e-4 1e-3
============  ================================  ====================  ======================

"Hidden size" is read as the token width ``d`` (the feed-forward width follows as ``4 d``).
The ``small`` preset's smaller frames (160x96) make the larger patches cover more of a frame
than at the paper's 320x180.

Budget (``--budget``, default 20 min, the whole script): the ``small`` preset
(:data:`uavcal_jax.calib.presets.PRESETS`) with a window every 10 s (non-overlapping at the
preset's 10 s; the window grid keeps that stride, as the paper keeps its 1 s, so every window
length has as many windows and steps per epoch), 2 seeds, and each grid at the reduced
resolution of the table's budget column: the preset's value and one other (the cheaper end of
a Table 5 grid, the shorter window of Table 1), every value of the optimisation grids
(``--full-grid``: every value). That is 14 distinct fits, each a compile of its own (1-3 min on
2 shared cores the first time, seconds once in the persistent XLA cache: a first run pays them
out of its budget). Every fit first runs two epochs, then all are raised together to a common
epoch count that fills the time left (:mod:`uavcal_jax.calib.schedule`): every point of a
grid trains equally long. On 2 shared CPU cores (warm cache) the two first epochs of the 14
fits (~106 training windows, 7 steps an epoch) and their evaluations take the whole default
budget, more when the cores are busier: it checks the pipeline and the baselines, and
``--budget 150`` or ``--grids`` subsets buy epochs. ``--paper`` selects the ``paper`` preset
(Table 2), every value of every grid and the full epochs instead.

Usage::

    python experiments/calib_ablation.py                         # budget mode, all grids
    python experiments/calib_ablation.py --grids window,lr,norm_first --seeds 4 --budget 60
    python experiments/calib_ablation.py --full-grid --budget 600
    python experiments/calib_ablation.py --paper                 # Table 2, full epochs
    python experiments/calib_ablation.py --budget 3 --max-duration 30 --grids layers,sign \\
        --sequences MH_01_easy,V1_01_easy,MH_03_medium          # a smoke run

Writes ``OUT/table.md``, ``OUT/results.json``, ``OUT/fig3_<grid>.png`` and the run folders
``OUT/runs/<grid>/<value>``; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from _calib_common import (  # the script's folder is first on sys.path
    ROOT,
    add_common_arguments,
    budget_record,
    describe,
    fmt_mean_std,
    log,
    mode_line,
    names_list,
    pick_sequences,
    render,
    resolve,
)
from _docs import write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.calib.config import PROTOCOLS
from uavcal_jax.calib.data import count_windows, load_windows
from uavcal_jax.calib.schedule import Budget, Job, evaluate_best, train_jobs
from uavcal_jax.calib.trials import mean_std_of, write_trial_data
from uavcal_jax.config import to_dict
from uavcal_jax.sim.training_sets import FAMILIES
from uavcal_jax.xla_cache import enable_compilation_cache


@dataclass(frozen=True)
class Grid:
    key: str
    label: str
    table: str
    budget: tuple
    full: tuple

    def setting(self, value) -> str:
        """The ``--set`` string of one value (square patches)."""
        return f"{self.key}={value},{value}" if self.key == "model.patch" else \
            f"{self.key}={value}"


GRIDS = {
    "window": Grid("window.duration", "window length (s)", "Table 1", (2, 10),
                   (2, 4, 6, 8, 10)),
    "dropout": Grid("model.dropout", "dropout", "Table 5", (0.01, 0.2),
                    (0.0, 0.01, 0.05, 0.1, 0.2)),
    "hidden": Grid("model.d_model", "hidden size d", "Table 5", (32, 64),
                   (32, 64, 128, 256, 512)),
    "heads": Grid("model.heads", "attention heads", "Table 5", (1, 4), (1, 2, 4, 8, 16)),
    "layers": Grid("model.layers", "layers", "Table 5", (1, 2), (1, 2, 3, 4, 5, 6, 7)),
    "noise": Grid("injection.noise_multiplier", "noise multiplier n_m", "Table 5", (1, 2),
                  (1, 2, 3, 4)),
    "patch": Grid("model.patch", "patch size (px)", "Table 5", (32, 64),
                  (32, 64, 96, 128)),
    "sign": Grid("loss.sign_term", "sign term of the loss", "surrogate", ("sign", "tanh"),
                 ("sign", "tanh")),
    "standardize": Grid("model.standardize", "standardised IMU and offsets", "optimisation",
                        (False, True), (False, True)),
    "norm_first": Grid("model.norm_first", "pre-norm layers", "optimisation", (False, True),
                       (False, True)),
    "units": Grid("loss.units", "loss units", "optimisation", ("si", "standardized"),
                  ("si", "standardized")),
    "lr": Grid("train.learning_rate", "AdamW learning rate", "optimisation",
               (1e-5, 1e-4, 1e-3), (1e-5, 1e-4, 1e-3)),
}
#: Held-out sequences per family (about a fifth of each set's duration).
VAL_SEQUENCES = {"euroc": ("MH_03_medium", "V2_02_medium"),
                 "uzh_fpv": ("indoor_45_4", "indoor_forward_3")}


def _field(config_dict: dict, key: str):
    """The value of ``section.field`` in a resolved configuration dict."""
    section, name = key.split(".")
    value = config_dict[section][name]
    return value[0] if key == "model.patch" else value


class Loader:
    """``(train, val)`` windows per window configuration, loaded on first use; ``keep``: how
    many configurations stay in memory (``None``: all)."""

    def __init__(self, folders: list[Path], is_val: list[bool], keep: int | None):
        self.folders, self.is_val, self.keep = folders, is_val, keep
        self.cache: dict = {}

    def __call__(self, window):
        if window not in self.cache:
            if self.keep is not None:
                while len(self.cache) >= self.keep:
                    self.cache.pop(next(iter(self.cache)))
            parts = load_windows(self.folders, window)
            self.cache[window] = ([p for p, v in zip(parts, self.is_val, strict=True) if not v],
                                  [p for p, v in zip(parts, self.is_val, strict=True) if v])
        return self.cache[window]


def plot_figure3(path, grid: Grid, rows: list[dict], default) -> str:
    """Figure 3: validation offset RMSE and sign F1 (mean ± std over seeds) against the
    grid's value, the two baselines dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    numeric = all(isinstance(r["value"], int | float) and not isinstance(r["value"], bool)
                  for r in rows)
    x = [r["value"] for r in rows] if numeric else list(range(len(rows)))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, key, scale, label in ((axes[0], "offset_rmse", 1.0, "val offset RMSE"),
                                  (axes[1], "sign_f1", 100.0, "val sign F1 (%)")):
        m = [np.nan if r[key] is None else r[key]["mean"] * scale for r in rows]
        s = [np.nan if r[key] is None else r[key]["std"] * scale for r in rows]
        ax.errorbar(x, m, yerr=s, marker="o", capsize=3, label="transformer")
        for base, style, name in (("mean_offset", "k--", "mean offset"),
                                  ("window_mean", "k:", "window mean")):
            ax.plot(x, [r[base][key] * scale for r in rows], style, lw=1, label=name)
        if key == "offset_rmse":
            ax.legend(fontsize=8)
        if default in [r["value"] for r in rows]:
            ax.axvline(x[[r["value"] for r in rows].index(default)], color="0.7", lw=0.8)
        if grid.key == "train.learning_rate":
            ax.set_xscale("log")
        ax.set_xticks(x, [str(r["value"]) for r in rows])
        ax.set_xlabel(grid.label)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{grid.table} analogue: {grid.label} (mean ± std over seeds)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def _arguments() -> tuple[argparse.ArgumentParser, argparse.Namespace, list[str]]:
    """``(parser, args, grids)``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, ROOT / "experiments" / "out" / "calib_ablation")
    ap.add_argument("--grids", default=",".join(GRIDS),
                    help="comma-separated subset of %(default)s")
    ap.add_argument("--full-grid", action="store_true",
                    help="every value of each grid (the full grid column); --paper implies it "
                         "[default: the budget column]")
    ap.add_argument("--seeds", type=positive_int, default=2,
                    help="K models per grid point, vmapped [default: %(default)s]")
    ap.add_argument("--family", choices=FAMILIES[:2], default="euroc",
                    help="simulated set [default: %(default)s]")
    ap.add_argument("--val-sequences", type=names_list, default=None, metavar="A,B,...",
                    help="held-out sequences [default: "
                         + "; ".join(f"{f}: {','.join(v)}" for f, v in VAL_SEQUENCES.items())
                         + "]")
    ap.add_argument("--protocol", choices=PROTOCOLS, default="paper",
                    help="offset injection [default: %(default)s]")
    args = ap.parse_args()
    grids = [g for g in args.grids.split(",") if g]
    if any(g not in GRIDS for g in grids):
        ap.error(f"unknown grids: {[g for g in grids if g not in GRIDS]}; one of {list(GRIDS)}")
    return ap, args, grids


def _plan(args, grids: list[str], full: bool, loader: Loader) -> tuple[list[Job], list]:
    """``(jobs, points)``: one ``(grid, value, window, job)`` per grid point; a value equal to
    the base configuration's is one fit shared by every grid holding it, in the run folder
    ``OUT/runs/<grid>/<value>`` of its first point."""
    by_config: dict = {}
    points = []
    for g in grids:
        grid = GRIDS[g]
        for value in (grid.full if full else grid.budget):
            calib, loop, window = resolve(args, [grid.setting(value)], protocol=args.protocol,
                                          seeds=args.seeds, epochs=args.max_epochs)
            key = (calib, loop, window)
            if key not in by_config:
                run_dir = args.out / "runs" / g / str(value)
                run_dir.mkdir(parents=True, exist_ok=True)
                by_config[key] = Job(f"{g}={value}", calib, loop,
                                     lambda window=window: loader(window), run_dir)
            points.append((g, value, window, by_config[key]))
    return list(by_config.values()), points


def _grid_rows(grids: list[str], points: list, evals: dict, info: dict) -> dict[str, list]:
    """Per grid, one row per point: its training, mean ± std over the seeds of the validation
    offset RMSE and sign F1, and the two baselines'."""
    tables = {}
    for g in grids:
        rows = []
        for pg, value, _, job in points:
            if pg != g:
                continue
            ev = evals[job.name]
            rows.append({"value": value, "epochs": job.epochs,
                         "best_epoch": job.summary["best_epoch"], "stopped_early": job.stopped,
                         **info[job.name],
                         **mean_std_of(ev["metrics"], ("offset_rmse", "sign_f1")),
                         "mean_offset": _headline(ev["baseline_mean_offset"]),
                         "window_mean": _headline(ev["baseline_window_mean"]),
                         "val_loss": ev["loss"], "train_loss": job.summary["best"].get("loss"),
                         "offsets": ev["offsets"], "run": str(job.run_dir)})
        tables[g] = rows
    return tables


def main() -> None:
    ap, args, grids = _arguments()
    full = args.full_grid or args.paper
    val_names = set(args.val_sequences or VAL_SEQUENCES[args.family])

    budget = Budget(None if args.paper else args.budget)
    enable_compilation_cache()
    base, _, base_window = resolve(args, protocol=args.protocol, seeds=args.seeds,
                                   epochs=args.max_epochs)
    base_dict = {**to_dict(base), "window": dataclasses.asdict(base_window)}
    names = pick_sequences(args.family, args.sequences)
    if not val_names & set(names) or not set(names) - val_names:
        ap.error(f"the {args.family} sequences {names} leave no held-out ({sorted(val_names)}) "
                 "or no training sequence")
    folders = render(args.family, names, args.max_duration, args.cache, args.quiet)
    # the paper mode's fits run one at a time to the end: one window set in memory at once
    loader = Loader(folders, [n in val_names for n in names], keep=1 if args.paper else None)
    shutil.rmtree(args.out / "runs", ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    jobs, points = _plan(args, grids, full, loader)
    info: dict = {}

    def after_first(job, _res):
        # the data of a point is fixed: record it while it is loaded (paper mode loads lazily)
        train, val = job.data()
        write_trial_data(job.run_dir, train, val)
        info[job.name] = {"train_windows": count_windows(train),
                          "val_windows": count_windows(val),
                          "frames_per_window": train[0].windows.frames_per_window}
    t_data = budget.elapsed()
    log(args.quiet, f"{len(points)} grid points ({len(jobs)} distinct fits) x {args.seeds} "
                    f"seeds; data ready in {t_data:.0f} s; "
                    f"{'no time limit' if args.paper else f'{budget.left() / 60:.1f} min left'}")
    schedule = train_jobs(jobs, budget, reserve_s=5.0, quiet=args.quiet,
                          after_first=after_first)
    evals = {job.name: evaluate_best(job, quiet=args.quiet)[2] for job in jobs}
    tables = _grid_rows(grids, points, evals, info)
    plots = [plot_figure3(args.out / f"fig3_{g}.png", GRIDS[g], rows,
                          _field(base_dict, GRIDS[g].key)) for g, rows in tables.items()]

    rec_budget = budget_record(budget, args.paper)
    T = next((info[j.name]["frames_per_window"] for _, _, w, j in points if w == base_window),
             None)
    settings = {"preset": "paper" if args.paper else "small", "sets": args.set,
                "seeds": args.seeds, "family": args.family, "sequences": names,
                "val_sequences": sorted(val_names & set(names)), "protocol": args.protocol,
                "full_grid": full, "max_duration_s": args.max_duration,
                "val_offsets": jobs[0].loop.val_offsets,
                "max_epochs": base.train.epochs, "describe": describe(base, base_window, T)}
    table = _table(tables, base_dict, settings, rec_budget, schedule, args)
    (args.out / "table.md").write_text(table)
    write_docs(args, "calib_ablation", table,
               anchor="Avola et al. 2023, Tables 1 and 5 (UZH-FPV 80/20)")
    (args.out / "results.json").write_text(json.dumps(
        {"script": "experiments/calib_ablation.py", "argv": sys.argv[1:], **rec_budget,
         "data_s": round(t_data, 1), "settings": settings, "schedule": schedule,
         "grids": {g: {"key": GRIDS[g].key, "default": _field(base_dict, GRIDS[g].key),
                       "rows": rows} for g, rows in tables.items()},
         "plots": plots, "table": str(args.out / "table.md")}, indent=1) + "\n")
    if not args.quiet:
        print(table)
    print_json({"table": str(args.out / "table.md"), "json": str(args.out / "results.json"),
                "plots": plots, **rec_budget, "target_epochs": schedule["target_epochs"],
                "grids": {g: {str(r["value"]): {
                    "offset_rmse": _round(r["offset_rmse"], "mean"),
                    "offset_rmse_std": _round(r["offset_rmse"], "std"),
                    "sign_f1": _round(r["sign_f1"], "mean"),
                    "sign_f1_std": _round(r["sign_f1"], "std"),
                    "window_mean_offset_rmse": round(r["window_mean"]["offset_rmse"], 5)}
                    for r in rows} for g, rows in tables.items()}})


def _headline(metrics: dict) -> dict:
    return {"offset_rmse": metrics["offset_rmse"], "sign_f1": metrics["sign_f1"]}


def _round(stat: dict | None, key: str):
    return None if stat is None else round(stat[key], 5)


def _table(tables, base_dict, settings, rec_budget, schedule, args) -> str:
    lines = ["# Calibrator ablations (Tables 1 and 5 analogue, optimisation choices)", "",
             f"- {mode_line(rec_budget, schedule, settings['max_epochs'], 'every grid point')}"
             ".",
             f"- Base configuration: {settings['describe']}; one field changed per grid "
             "point (starred: the base value); "
             + ("every value of each grid." if settings["full_grid"] else
                "each grid at its reduced budget resolution (`--full-grid`: every value)."),
             f"- Data: simulated {args.family} set ({len(settings['sequences'])} sequences, "
             + ("whole trajectories" if args.max_duration is None else
                f"each capped at {args.max_duration:g} s")
             + f"); held out for validation: {', '.join(settings['val_sequences'])} (whole "
             "sequences, fixed); trained on the others.",
             f"- {args.seeds} seeds vmapped per point: mean ± std over seeds at the best epoch, "
             f"every held-out window evaluated once per offset with {settings['val_offsets']} "
             f"offsets drawn by the point's protocol ({args.protocol}). Offset RMSE pools gyro "
             "(rad/s) and accel (m/s^2), as the paper. Baselines on the same windows and "
             "offsets: the mean offset, and the window mean (each window's mean IMU sample "
             "minus the training set's).", ""]
    for g, rows in tables.items():
        grid = GRIDS[g]
        default = _field(base_dict, grid.key)
        lines += [f"## {g}: {grid.label} (`{grid.key}`, {grid.table})", "",
                  f"| {grid.label} | epochs (best) | windows train / val | frames per window | "
                  "val offset RMSE | val sign F1 (%) | mean-offset RMSE | window-mean RMSE |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            star = "*" if r["value"] == default else ""
            lines.append(f"| {r['value']}{star} | {r['epochs']} ({r['best_epoch']}) | "
                         f"{r['train_windows']} / {r['val_windows']} | "
                         f"{r['frames_per_window']} | {fmt_mean_std(r['offset_rmse'])} | "
                         f"{fmt_mean_std(r['sign_f1'], 100, 2)} | "
                         f"{r['mean_offset']['offset_rmse']:.3f} | "
                         f"{r['window_mean']['offset_rmse']:.3f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
