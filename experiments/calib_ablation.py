"""The calibrator's ablations: the grids of Table 1 (window length) and Table 5 (dropout,
hidden size, heads, layers, noise multiplier, patch size) of Avola et al. (Sensors 2023), plus
the sign-loss surrogate against the exact sign term, with Figure 3's metric-against-value
plots.

Every grid point is one ``uavcal calib train`` fit: the mode's configuration with one field
changed, ``K`` seeds vmapped (``--seeds``, ``train.seeds``), on the fixed random 80/20 split
over the windows of the simulated set (``LoopConfig(validation="split")``), one injected
validation offset (seed ``train.seed``), best epoch by training loss (the paper's early
stopping). Reported per grid point: mean ± std over the ``K`` seeds of the validation offset
RMSE and sign F1 at the best epoch, beside the mean-offset baseline.

Grids (``--grids``; the value of the mode's configuration is starred in the table):

==========  ==============================  =================  ======================
grid        field                           budget values      paper values
==========  ==============================  =================  ======================
window      ``window.duration`` (s)         2 4 6 8 10         2 4 6 8 10
dropout     ``model.dropout``               0 .01 .05 .1 .2    0 .01 .05 .1 .2
hidden      ``model.d_model``               32 64 128          64 128 256 512
heads       ``model.heads``                 1 2 4 8 16         1 2 4 8 16
layers      ``model.layers``                1 ... 7            1 ... 7
noise       ``injection.noise_multiplier``  1 2 3 4            1 2 3 4
patch       ``model.patch`` (square, px)    32 64 96 128       32 64 96 128
sign        ``loss.sign_term``              sign tanh          sign tanh
==========  ==============================  =================  ======================

"Hidden size" is read as the token width ``d`` (the feed-forward width follows as ``4 d``).
The budget mode's smaller frames (160x96) make the larger patches cover more of a frame than
at the paper's 320x180.

Budget (``--budget``, default 20 min, the whole script): the reduced configuration of
``_calib_common.BUDGET_SETTINGS`` with windows every 2 s, every 4th frame (5 Hz,
:data:`BUDGET_EXTRA`, :data:`BUDGET_FRAME_STEP`) and 2 seeds; every grid point first runs two
epochs, then all are raised together to a common epoch count that fills the time left (see
``experiments/_calib_common.py``): every point of a grid trains equally long. ``--paper``
selects Table 2's configuration and its full epochs instead.

Usage::

    python experiments/calib_ablation.py                         # budget mode, all grids
    python experiments/calib_ablation.py --grids window,sign --seeds 4
    python experiments/calib_ablation.py --paper                 # Table 2, full epochs
    python experiments/calib_ablation.py --budget 3 --max-duration 20 \\
        --sequences MH_01_easy,V1_01_easy --grids layers,sign   # a smoke run

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

import numpy as np
from _calib_common import (  # the script's folder is first on sys.path
    ROOT,
    Budget,
    Job,
    add_common_arguments,
    best_row,
    budget_record,
    describe,
    fmt_mean_std,
    load_parts,
    log,
    mode_settings,
    pick_sequences,
    render,
    train_jobs,
)

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.calib.config import PROTOCOLS, config_to_dict
from uavcal_jax.calib.protocols import mean_std, resolve_configs, trial_sides, validation_trials
from uavcal_jax.calib.sim_sets import FAMILIES
from uavcal_jax.xla_cache import enable_compilation_cache

#: Budget mode's window stride and frame step: windows every 2 s, 5 Hz frames (10 per 2 s
#: window, 50 per 10 s one). Smoke-run figures on 2 cores: a 2-seed step takes ~0.06 s at 10
#: frames, ~0.19 s at 50, so an epoch of all 28 distinct fits over the whole simulated EuRoC
#: set (~670 windows) is ~2 min; a new configuration's compile takes 15-75 s (7 layers), about
#: 10 min for all of them on a first run, ~7 s each once in the persistent XLA cache.
BUDGET_EXTRA = ("window.stride=2",)
BUDGET_FRAME_STEP = 4


@dataclass(frozen=True)
class Grid:
    key: str
    label: str
    table: str
    budget: tuple
    paper: tuple

    def values(self, paper: bool) -> tuple:
        return self.paper if paper else self.budget

    def setting(self, value) -> str:
        """The ``--set`` string of one value (square patches)."""
        return f"{self.key}={value},{value}" if self.key == "model.patch" else \
            f"{self.key}={value}"


GRIDS = {
    "window": Grid("window.duration", "window length (s)", "Table 1", (2, 4, 6, 8, 10),
                   (2, 4, 6, 8, 10)),
    "dropout": Grid("model.dropout", "dropout", "Table 5", (0.0, 0.01, 0.05, 0.1, 0.2),
                    (0.0, 0.01, 0.05, 0.1, 0.2)),
    "hidden": Grid("model.d_model", "hidden size d", "Table 5", (32, 64, 128),
                   (64, 128, 256, 512)),
    "heads": Grid("model.heads", "attention heads", "Table 5", (1, 2, 4, 8, 16),
                  (1, 2, 4, 8, 16)),
    "layers": Grid("model.layers", "layers", "Table 5", (1, 2, 3, 4, 5, 6, 7),
                   (1, 2, 3, 4, 5, 6, 7)),
    "noise": Grid("injection.noise_multiplier", "noise multiplier n_m", "Table 5",
                  (1, 2, 3, 4), (1, 2, 3, 4)),
    "patch": Grid("model.patch", "patch size (px)", "Table 5", (32, 64, 96, 128),
                  (32, 64, 96, 128)),
    "sign": Grid("loss.sign_term", "sign term of the loss", "surrogate", ("sign", "tanh"),
                 ("sign", "tanh")),
}


def _field(config_dict: dict, key: str):
    """The value of ``section.field`` in a resolved configuration dict."""
    section, name = key.split(".")
    value = config_dict[section][name]
    return value[0] if key == "model.patch" else value


class Loader:
    """Windows per window configuration, loaded on first use; ``keep``: how many
    configurations stay in memory (``None``: all)."""

    def __init__(self, folders, frame_step: int, keep: int | None):
        self.folders, self.frame_step, self.keep = folders, frame_step, keep
        self.cache: dict = {}

    def __call__(self, window):
        if window not in self.cache:
            if self.keep is not None:
                while len(self.cache) >= self.keep:
                    self.cache.pop(next(iter(self.cache)))
            self.cache[window] = load_parts(self.folders, window, self.frame_step)
        return self.cache[window]


def plot_figure3(path, grid: Grid, rows: list[dict], default) -> str:
    """Figure 3: validation offset RMSE and sign F1 (mean ± std over seeds) against the
    grid's value, the mean-offset baseline's RMSE dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    numeric = all(isinstance(r["value"], int | float) for r in rows)
    x = [r["value"] for r in rows] if numeric else list(range(len(rows)))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, key, scale, label in ((axes[0], "offset_rmse", 1.0, "val offset RMSE"),
                                  (axes[1], "sign_f1", 100.0, "val sign F1 (%)")):
        m = [np.nan if r[key] is None else r[key]["mean"] * scale for r in rows]
        s = [np.nan if r[key] is None else r[key]["std"] * scale for r in rows]
        ax.errorbar(x, m, yerr=s, marker="o", capsize=3, label="transformer")
        if key == "offset_rmse":
            ax.plot(x, [r["baseline_offset_rmse"] for r in rows], "k--", lw=1,
                    label="mean-offset baseline")
            ax.legend(fontsize=8)
        if default in [r["value"] for r in rows]:
            ax.axvline(x[[r["value"] for r in rows].index(default)], color="0.7", lw=0.8)
        ax.set_xticks(x, [str(r["value"]) for r in rows])
        ax.set_xlabel(grid.label)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{grid.table} analogue: {grid.label} (mean ± std over seeds)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, ROOT / "experiments" / "out" / "calib_ablation",
                         budget_frame_step=BUDGET_FRAME_STEP)
    ap.add_argument("--grids", default=",".join(GRIDS),
                    help="comma-separated subset of %(default)s")
    ap.add_argument("--seeds", type=positive_int, default=2,
                    help="K models per grid point, vmapped [default: %(default)s]")
    ap.add_argument("--family", choices=FAMILIES[:2], default="euroc",
                    help="simulated set [default: %(default)s]")
    ap.add_argument("--protocol", choices=PROTOCOLS, default="paper",
                    help="offset injection [default: %(default)s]")
    args = ap.parse_args()
    grids = [g for g in args.grids.split(",") if g]
    if any(g not in GRIDS for g in grids):
        ap.error(f"unknown grids: {[g for g in grids if g not in GRIDS]}; one of {list(GRIDS)}")

    budget = Budget(None if args.paper else args.budget)
    enable_compilation_cache()
    sets = mode_settings(args, BUDGET_EXTRA)
    base, _, base_window = resolve_configs(sets, protocol=args.protocol, validation="split",
                                        seeds=args.seeds, epochs=args.max_epochs)
    base_dict = {**config_to_dict(base), "window": dataclasses.asdict(base_window)}
    names = pick_sequences(args.family, args.sequences)
    if not names:
        ap.error(f"--sequences keeps no {args.family} sequence")
    folders = render(args.family, names, args.max_duration, args.cache, args.quiet)
    # the paper mode's fits run one at a time to the end: one window set in memory at once
    loader = Loader(folders, args.frame_step, keep=1 if args.paper else None)
    shutil.rmtree(args.out / "runs", ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)

    # a value equal to the base configuration's is one fit shared by every grid holding it
    by_config: dict = {}
    points = []
    for g in grids:
        grid = GRIDS[g]
        for value in grid.values(args.paper):
            calib, loop, window = resolve_configs([*sets, grid.setting(value)],
                                               protocol=args.protocol, validation="split",
                                               seeds=args.seeds, epochs=args.max_epochs)

            def data(window=window, loop=loop):
                return validation_trials(loader(window), loop)[0]

            key = (calib, loop, window)
            if key not in by_config:
                run_dir = args.out / "runs" / g / str(value)
                run_dir.mkdir(parents=True, exist_ok=True)
                by_config[key] = Job(f"{g}={value}", calib, loop, data, run_dir)
            points.append((g, value, window, by_config[key]))
    jobs = list(by_config.values())
    info: dict = {}

    def after_first(job, _res):
        # the data of a point is fixed: record it while it is loaded (paper mode loads lazily)
        train, val = job.data()
        (job.run_dir / "data.json").write_text(json.dumps(trial_sides(train, val)) + "\n")
        info[job.name] = {"train_windows": int(sum(len(p.indices) for p in train)),
                          "val_windows": int(sum(len(p.indices) for p in val)),
                          "frames_per_window": train[0].windows.frames_per_window}
    t_data = budget.elapsed()
    log(args.quiet, f"{len(points)} grid points ({len(jobs)} distinct fits) x {args.seeds} "
                    f"seeds; data ready in "
                    f"{t_data:.0f} s; "
                    f"{'no time limit' if args.paper else f'{budget.left() / 60:.1f} min left'}")
    schedule = train_jobs(jobs, budget, reserve_s=5.0, quiet=args.quiet,
                          after_first=after_first)

    tables, plots = {}, []
    for g in grids:
        rows = []
        for pg, value, _, job in points:
            if pg != g:
                continue
            row = best_row(job)
            rows.append({"value": value, "epochs": job.epochs, "best_epoch": row["epoch"],
                         "stopped_early": job.stopped, **info[job.name],
                         "offset_rmse": mean_std([m["offset_rmse"] for m in row["val_metrics"]]),
                         "sign_f1": mean_std([m["sign_f1"] for m in row["val_metrics"]]),
                         "baseline_offset_rmse": row["baseline_offset_rmse"],
                         "val_loss": row["val_loss"], "train_loss": row["loss"],
                         "run": str(job.run_dir)})
        tables[g] = rows
        plots.append(plot_figure3(args.out / f"fig3_{g}.png", GRIDS[g], rows,
                                  _field(base_dict, GRIDS[g].key)))

    rec_budget = budget_record(budget, args.paper, args.budget)
    T = next((info[j.name]["frames_per_window"] for _, _, w, j in points if w == base_window),
             None)
    settings = {"sets": sets, "seeds": args.seeds, "family": args.family,
                "sequences": names, "protocol": args.protocol, "frame_step": args.frame_step,
                "max_duration_s": args.max_duration, "split": "80/20 over windows, seed 0",
                "max_epochs": base.train.epochs,
                "describe": describe(base, base_window, T, args.frame_step)}
    table = _table(tables, base_dict, settings, rec_budget, schedule, args)
    (args.out / "table.md").write_text(table)
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
                    "offset_rmse": None if r["offset_rmse"] is None else
                    round(r["offset_rmse"]["mean"], 5),
                    "offset_rmse_std": None if r["offset_rmse"] is None else
                    round(r["offset_rmse"]["std"], 5),
                    "sign_f1": None if r["sign_f1"] is None else round(r["sign_f1"]["mean"], 5),
                    "sign_f1_std": None if r["sign_f1"] is None else
                    round(r["sign_f1"]["std"], 5)} for r in rows}
                    for g, rows in tables.items()}})


def _table(tables, base_dict, settings, rec_budget, schedule, args) -> str:
    mode = (f"paper mode (Table 2 configuration, at most {settings['max_epochs']} epochs, "
            "early stopping)" if args.paper else
            f"budget mode: {rec_budget['budget_min']:g} min for the whole script (took "
            f"{rec_budget['wall_s'] / 60:.1f} min); every grid point "
            f"{schedule['target_epochs']} epochs at most (two first, then a common count that "
            "fills the time left), best epoch by training loss")
    lines = ["# Calibrator ablations (Tables 1 and 5 analogue)", "",
             f"- {mode}.",
             f"- Base configuration: {settings['describe']}; one field changed per grid "
             "point (starred: the base value).",
             f"- Data: simulated {args.family} set ({len(settings['sequences'])} sequences: "
             f"{', '.join(settings['sequences'])}; "
             + ("whole trajectories" if args.max_duration is None else
                f"each capped at {args.max_duration:g} s")
             + "), fixed random 80/20 split over windows; one injected validation offset.",
             f"- {args.seeds} seeds vmapped per point: mean ± std over seeds at the best epoch. "
             "Offset RMSE pools gyro (rad/s) and accel (m/s^2), as the paper.", ""]
    for g, rows in tables.items():
        grid = GRIDS[g]
        default = _field(base_dict, grid.key)
        lines += [f"## {g}: {grid.label} (`{grid.key}`, {grid.table})", "",
                  f"| {grid.label} | epochs (best) | windows train / val | frames per window | "
                  "val offset RMSE | val sign F1 (%) | mean-offset baseline RMSE |",
                  "|---|---|---|---|---|---|---|"]
        for r in rows:
            star = "*" if r["value"] == default else ""
            lines.append(f"| {r['value']}{star} | {r['epochs']} ({r['best_epoch']}) | "
                         f"{r['train_windows']} / {r['val_windows']} | "
                         f"{r['frames_per_window']} | {fmt_mean_std(r['offset_rmse'])} | "
                         f"{fmt_mean_std(r['sign_f1'], 100, 2)} | "
                         f"{r['baseline_offset_rmse']:.3f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
