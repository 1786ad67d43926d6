"""The calibrator's validation protocols beside its baselines: the Table 4 analogue of Avola et
al. (Sensors 2023), with Figure 2's predicted-against-true offsets.

Experiments (``--experiments``): leave-one-sequence-out on the simulated EuRoC set
(``euroc_loo``) and on the simulated UZH-FPV set (``uzh_fpv_loo``), and k-fold over the
windows of one long sequence, MH_01_easy (``mh01_kfold``; contiguous blocks); each under the
paper's injection protocol and the physical one (``--protocols``). ``--trials N`` keeps N
trials of each experiment spread evenly over it (held-out sequences of a LOO in set order,
folds of the k-fold; the folder ``trial_NN`` keeps the trial's index among all of them, as
``uavcal calib train --validation loo`` numbers it); ``--trials all`` runs every one.

Methods, all on the same validation windows, each window evaluated once per offset with the
same ``K = loop.val_offsets`` (8) offsets, each offset shared by every window of the trial (the
paper's convention) and drawn by the protocol (:func:`uavcal_jax.calib.loop.evaluate`):

- ``transformer``: the video + IMU calibrator, its best epoch (``uavcal calib train``'s fit);
- ``imu_only``: the same without the video reducer (``model.use_video=false``);
- ``closed_form``: the transformer whose head learns a correction to the window mean below
  (``model.closed_form=window_mean``; its untrained prediction is that baseline);
- ``motion_tokens``: the shipped design (:data:`uavcal_jax.calib.presets.SHIPPED`): rotation-
  residual tokens from the front end's visual rotations (``window.rotations=visual``, cached
  beside each recording) and a head that starts at their gyro least squares, on the
  accelerometer at the mean offset (physical protocol) or the window mean (paper protocol,
  ``model.closed_form=rotation_window_mean``);
- ``motion_tilt``: ``motion_tokens`` with the auxiliary tilt head (``model.tilt_head``:
  gravity's direction in the IMU frame per frame, learned from the ground truth);
- ``mean_offset``: the mean of the protocol's training offsets, for every window;
- ``window_mean``: each window's mean IMU sample minus the training set's mean (no learning;
  right where the window's motion averages out and gravity's projection matches the training
  set's mean);
- ``vio_bias``, ``visual_ls`` and ``self_calib`` (physical protocol only,
  ``--blind-offsets``): the estimators that need no ground truth, ``uavcal calib predict
  --method vio-bias`` (the VIO's bias states), ``visual-ls`` (the gyro's least squares
  against the camera's rotations) and ``self-calib`` (descending through the VIO's own
  windows, their biases pinned),
  each on the whole held-out recording with the trial's first offsets injected into its IMU;
  scored against the ``total`` label over the span each used;
- ``least_squares``: the classical constant-offset fit of each window's full-rate IMU against
  the ground-truth states (:func:`uavcal_jax.calib.baselines.least_squares_windows`); it
  estimates the stream's whole constant error, i.e. the injected offset **plus** the
  simulated IMU's own turn-on bias, which the calibrator is not asked for;
- ``least_squares_oracle``: the same minus the true bias (from the ground truth): the
  injected offset as least squares sees it, an upper bound no method here can reach blind.

Every trial trains with ``train.seed = --seed``, as ``uavcal calib train --validation loo``
does: the K offsets are then drawn from that seed and, for the paper protocol, the trial's
training statistics, so the physical protocol injects the same K offsets into every trial.
``--trial-seeds`` gives trial ``i`` the seed ``--seed + i`` (its own offsets), at the price of
one compile per trial (the seed is part of the jitted steps' static configuration). Reported:
mean and standard deviation over trials of sign F1 and offset RMSE (gyro rad/s and accel
m/s^2 pooled, as the paper; the per-sensor RMSEs beside), next to the paper's Table 4.

Budget (``--budget``, default 20 min, the whole script): the ``small`` preset
(:data:`uavcal_jax.calib.presets.PRESETS`: 160x96 frames in 32x32 patches at 10 Hz, d 64,
pre-norm, AdamW 1e-3) on non-overlapping 10 s windows, and 3 trials per experiment
(:data:`BUDGET_TRIALS`: 3 x 2 protocols x 2 models x 3 experiments = 36 fits). Every fit first
runs two epochs, then all are raised together to a common epoch count that fills the time
left (:mod:`uavcal_jax.calib.schedule`); the best checkpoint of each (by training loss)
is evaluated once at the end. On 2 shared CPU cores a video fit's epoch over the simulated
EuRoC set (~115 windows) takes ~15 s, a common epoch of the 36 fits ~4 min; loading the windows
(~2 min), least squares, the two first epochs and the final evaluations (~3.5 min) fill the
default budget: it measures the pipeline and the baselines at two epochs, and ``--budget 150``
buys some thirty.
``--paper`` selects the ``paper`` preset (Table 2: 320x180, 20 Hz, d 256, 1 s stride, lr
1e-5), every trial and the full epochs with early stopping instead. The simulated sets are
rendered into ``--cache`` once (the whole EuRoC and UZH-FPV sets take long: render them before
a timed run).

Usage::

    python experiments/calib_protocols.py                       # budget mode, 20 min
    python experiments/calib_protocols.py --budget 90 --trials 5
    python experiments/calib_protocols.py --paper               # Table 2, every trial
    python experiments/calib_protocols.py --budget 3 --max-duration 30 --trials 2 \\
        --sequences MH_01_easy,V1_01_easy,indoor_45_2,indoor_forward_3     # a smoke run

Writes ``OUT/table.md``, ``OUT/results.json``, ``OUT/fig2_<experiment>_<protocol>_trial_NN.png``
(the first of the K offsets) and the run folders ``OUT/runs/...`` (each readable by ``uavcal
calib eval``); the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
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
    pick_sequences,
    render,
    resolve,
)
from _docs import write_docs  # the script's folder is first on sys.path

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.calib.config import PROTOCOLS
from uavcal_jax.calib.data import count_windows, load_windows
from uavcal_jax.calib.loop import evaluate, mean_offset_baseline, validation_draws
from uavcal_jax.calib.metrics import seed_summary
from uavcal_jax.calib.predict import channel_names, predict_sequence
from uavcal_jax.calib.schedule import Budget, Job, evaluate_best, train_jobs
from uavcal_jax.calib.trials import (
    TRIAL_FORMAT,
    least_squares_trial,
    mean_std_of,
    spread,
    trial_dir,
    validation_trials,
    write_trial_data,
)
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.pipeline.motion_inputs import folder_sources
from uavcal_jax.pipeline.offset_scores import NO_CORRECTION, pooled_scores, score_recordings
from uavcal_jax.plots import plot_offsets
from uavcal_jax.xla_cache import enable_compilation_cache


@dataclass(frozen=True)
class Experiment:
    family: str
    validation: str
    only: tuple[str, ...] | None
    label: str
    #: The paper's Table 4 (sign F1 %, offset RMSE), its own protocol; None: not reported.
    paper: tuple[float, float] | None = None


EXPERIMENTS = {
    "euroc_loo": Experiment("euroc", "loo", None, "EuRoC (sim), leave one sequence out",
                            (94.59, 0.193)),
    "uzh_fpv_loo": Experiment("uzh_fpv", "loo", None, "UZH-FPV (sim), leave one sequence out",
                              (89.61, 0.502)),
    "mh01_kfold": Experiment("euroc", "kfold", ("MH_01_easy",),
                             "MH_01_easy (sim), k-fold over windows"),
}
#: Trained variants: their extra settings, per protocol (``None``: any protocol).
VARIANTS = {
    "transformer": {None: ()},
    "imu_only": {None: ("model.use_video=false",)},
    "closed_form": {None: ("model.closed_form=window_mean",)},
    # the shipped design (calib.presets.SHIPPED); under the paper protocol the head starts at
    # the window mean on the accelerometer, the protocol's strong no-learning estimate
    "motion_tokens": {
        "physical": ("model.motion_tokens=true", "model.closed_form=rotation_ls",
                     "model.correction_scale=0.05"),
        "paper": ("model.motion_tokens=true", "model.closed_form=rotation_window_mean")},
}
# the same with the auxiliary tilt head (gravity in the IMU frame per frame, issue 20)
VARIANTS["motion_tilt"] = {protocol: settings + ("model.tilt_head=true",)
                           for protocol, settings in VARIANTS["motion_tokens"].items()}
#: The variants whose windows need the camera's relative rotations (``window.rotations``).
VISUAL_VARIANTS = ("motion_tokens", "motion_tilt")
#: The estimators that need no ground truth and run on whole held-out recordings
#: (``uavcal calib predict --method``): table key -> registered method.
BLIND_METHODS = {"vio_bias": "vio-bias", "visual_ls": "visual-ls", "self_calib": "self-calib"}
METHODS = {
    "transformer": "transformer (video + IMU)",
    "imu_only": "transformer, IMU only",
    "closed_form": "transformer on the window mean (closed-form head)",
    "motion_tokens": "motion-token transformer (closed-form head)",
    "motion_tilt": "motion-token transformer with the tilt head (closed-form head)",
    "mean_offset": "mean-offset baseline",
    "window_mean": "window-mean baseline",
    "vio_bias": "VIO bias states (no ground truth)",
    "visual_ls": "visual rotations' gyro least squares (no ground truth)",
    "self_calib": "self-calibration through the VIO's windows (no ground truth)",
    "least_squares": "least squares vs ground-truth states",
    "least_squares_oracle": "least squares minus true IMU bias (oracle)",
}
#: Trials per experiment in budget mode (spread over the set); --paper runs every one.
BUDGET_TRIALS = 3
#: Seconds set aside per Figure 2 plot (predict with two models, draw).
PLOT_RESERVE_S = 15.0
#: The :func:`~uavcal_jax.calib.metrics.seed_summary` numbers averaged over trials.
HEADLINE = ("sign_f1", "offset_rmse", "gyro_rmse", "accel_rmse")


#: Figure 2's line of each method (:func:`uavcal_jax.plots.plot_offsets` draws it).
FIGURE2_STYLES = {"transformer": dict(color="C0", marker=".", ls="-", lw=1, ms=3),
                  "imu_only": dict(color="C1", marker=".", ls="-", lw=1, ms=3),
                  "closed_form": dict(color="C3", marker=".", ls="-", lw=1, ms=3),
                  "motion_tokens": dict(color="C4", marker=".", ls="-", lw=1, ms=3),
                  "motion_tilt": dict(color="C5", marker=".", ls="-", lw=1, ms=3),
                  "least_squares": dict(color="C2", ls="-", lw=1, ms=3),
                  "least_squares_oracle": dict(color="C2", ls=":", lw=1, ms=3),
                  "mean_offset": dict(color="0.5", ls="-.", lw=1, ms=3)}


def _parse_trials(text: str):
    return "all" if text == "all" else {int(v) for v in text.split(",") if v.strip()}


def _trial_count(text: str):
    return "all" if text == "all" else positive_int(text)


def _arguments() -> tuple[argparse.Namespace, list[str], list[str], int | None]:
    """``(args, experiments, protocols, trials per experiment or None for all)``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, ROOT / "experiments" / "out" / "calib_protocols")
    ap.add_argument("--experiments", default=",".join(EXPERIMENTS),
                    help="comma-separated subset of %(default)s")
    ap.add_argument("--protocols", default="paper,physical",
                    help=f"comma-separated injection protocols of {PROTOCOLS} "
                         "[default: %(default)s]")
    ap.add_argument("--trials", type=_trial_count, default=None, metavar="N|all",
                    help="trials per experiment, spread over it (LOO: held-out sequences; "
                         f"k-fold: folds used) [default: {BUDGET_TRIALS}, with --paper all]")
    ap.add_argument("--folds", type=positive_int, default=None,
                    help="k of mh01_kfold [default: LoopConfig.folds]")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="comma-separated trained variants of %(default)s")
    ap.add_argument("--seed", type=int, default=0, help="train.seed of every trial")
    ap.add_argument("--trial-seeds", action="store_true",
                    help="trial i trains with seed + i (its own validation offsets; one "
                         "compile per trial)")
    ap.add_argument("--blind-offsets", type=int, default=2, metavar="N",
                    help="physical protocol: the first N of each trial's offsets injected "
                         "into each held-out recording for the estimators that need no "
                         f"ground truth ({', '.join(BLIND_METHODS.values())}; one VIO run "
                         "per recording and offset); 0: none [default: %(default)s]")
    ap.add_argument("--plot-trials", type=_parse_trials, default={0}, metavar="I,J|all",
                    help="trials drawn as Figure 2, by their index among all the "
                         "experiment's trials (only those run) [default: 0]")
    args = ap.parse_args()
    experiments = [e for e in args.experiments.split(",") if e]
    protocols = [p for p in args.protocols.split(",") if p]
    args.variants = [v for v in args.variants.split(",") if v]
    bad = [e for e in experiments if e not in EXPERIMENTS] + [
        p for p in protocols if p not in PROTOCOLS] + [
        v for v in args.variants if v not in VARIANTS]
    if bad:
        ap.error(f"unknown experiments/protocols/variants: {bad}")
    if args.trials is None:
        n_trials = None if args.paper else BUDGET_TRIALS
    else:
        n_trials = None if args.trials == "all" else args.trials
    return args, experiments, protocols, n_trials


def _load(args, experiments: list[str], window) -> tuple[dict, dict, dict, dict]:
    """``(windows per experiment, sequence name per folder, skipped experiments, windows per
    folder)``: each folder's windows loaded once (MH_01_easy serves euroc_loo and
    mh01_kfold)."""
    loaded, skipped, exp_parts, seq_name = {}, {}, {}, {}
    for name in experiments:
        exp = EXPERIMENTS[name]
        names = pick_sequences(exp.family, args.sequences, exp.only)
        need = 2 if exp.validation == "loo" else 1
        if len(names) < need:
            skipped[name] = f"needs {need} sequence(s) of {exp.family}, --sequences left {names}"
            log(args.quiet, f"skipping {name}: {skipped[name]}")
            continue
        folders = render(exp.family, names, args.max_duration, args.cache, args.quiet)
        seq_name.update({str(Path(f).absolute()): n for n, f in zip(names, folders, strict=True)})
        for f in folders:
            if f not in loaded:
                (loaded[f],) = load_windows([f], window, **folder_sources(window))
        exp_parts[name] = [loaded[f] for f in folders]
    return exp_parts, seq_name, skipped, loaded


def _plan(args, exp_parts: dict, seq_name: dict, protocols: list[str], extra: list[str],
          n_trials: int | None) -> tuple[list[Job], dict, dict, dict]:
    """``(jobs, trials, trial key per job name, trials per experiment)``: one fit per
    experiment, protocol, trial run and variant, in the folder
    ``OUT/runs/<experiment>/<protocol>/<variant>/trial_NN`` with its ``data.json``."""
    jobs, trials, job_trial, trial_counts = [], {}, {}, {}
    for name, parts in exp_parts.items():
        for protocol in protocols:
            _, loop, _ = resolve(args, extra, protocol=protocol,
                                 validation=EXPERIMENTS[name].validation, epochs=args.max_epochs)
            every = validation_trials(parts, loop)
            trial_counts[name] = len(every)
            for i in spread(len(every), n_trials):
                train, val = every[i]
                key = (name, protocol, i)
                trials[key] = {"held_out": [seq_name[p.source] for p in val],
                               "train_windows": count_windows(train),
                               "val_windows": count_windows(val), "val": val, "jobs": {}}
                for variant in args.variants:
                    per_protocol = VARIANTS[variant]
                    settings = per_protocol.get(protocol, per_protocol.get(None, ()))
                    seed = args.seed + i if args.trial_seeds else args.seed
                    calib, _, _ = resolve(args, [*extra, f"train.seed={seed}", *settings],
                                          protocol=protocol, validation=loop.validation,
                                          epochs=args.max_epochs)
                    run = args.out / "runs" / name / protocol / variant
                    run_dir = write_trial_data(trial_dir(run, i, len(every)), train, val)
                    job = Job(f"{name}/{protocol}/{variant}/{TRIAL_FORMAT.format(i)}", calib,
                              loop, lambda t=train, v=val: (t, v), run_dir)
                    job_trial[job.name] = key
                    jobs.append(job)
                    trials[key]["jobs"][variant] = job
    return jobs, trials, job_trial, trial_counts


def _blind_trial(t: dict, n_offsets: int, quiet: bool) -> dict:
    """The estimators that need no ground truth (:data:`BLIND_METHODS`) on each held-out
    recording, once per each of the trial's first ``n_offsets`` offsets injected into its
    IMU (:func:`~uavcal_jax.pipeline.predict_offset.predict_offset`, ``total`` label: the
    offset plus the sensor's own bias over the span the estimate used): per method its
    :data:`HEADLINE` numbers pooled over the recordings and offsets (``None`` for a sensor
    it does not estimate), ``seconds`` and the ``rows``."""
    key_of = {method: key for key, method in BLIND_METHODS.items()}
    rows = []
    for j, offset in enumerate(t["offsets"][:n_offsets]):
        scored = score_recordings([part.source for part in t["val"]], BLIND_METHODS.values(),
                                  inject=np.asarray(offset, np.float64))
        for r in scored:  # one truth per recording and offset in pooled_scores
            rows.append({**r, "recording": f"{r['recording']}#{j}",
                         "method": key_of[r["method"]]})
            log(quiet, f"  {rows[-1]['method']} on {Path(r['recording']).name}, offset {j}: "
                       f"error {np.round(r['error'], 4).tolist()} ({r['seconds']} s)")
    out = {}
    for key, score in pooled_scores(rows).items():
        if key == NO_CORRECTION:
            continue
        rmse = list(score["rmse"].values())
        out[key] = {"sign_f1": score["sign_f1"], "gyro_rmse": score["gyro_rmse"],
                    "accel_rmse": score["accel_rmse"],
                    "offset_rmse": (float(np.sqrt(np.mean(np.square(rmse))))
                                    if len(rmse) == 6 else None),
                    "recordings": score["recordings"],
                    "seconds": sum(r["seconds"] for r in rows if r["method"] == key),
                    "rows": [r for r in rows if r["method"] == key]}
    return out


def _first_call(trials: dict, job_trial: dict, blind_offsets: int, quiet: bool):
    """``after_first`` of :func:`train_jobs`: the trial's K offsets (independent of training),
    least squares on the same windows with the same offsets and, under the physical
    protocol, the estimators that need no ground truth (:func:`_blind_trial`), once per
    trial."""
    gt_cache: dict[str, object] = {}

    def ground_truth(source: str):
        if source not in gt_cache:
            gt_cache[source] = read_euroc(source).ground_truth
        return gt_cache[source]

    def after_first(job, res):
        t = trials[job_trial[job.name]]
        offsets = validation_draws(res.state, job.config.train.seeds, job.loop.val_offsets)
        if "offsets" not in t:
            t0 = time.perf_counter()
            t.update(offsets=offsets, mean_offset_value=np.asarray(
                mean_offset_baseline(res.state, job.config.train.seeds)),
                least_squares=least_squares_trial(t["val"], offsets.astype(np.float64),
                                                  job.config.injection.single_sensor,
                                                  ground_truth))
            t["least_squares_s"] = round(time.perf_counter() - t0, 1)
            if job_trial[job.name][1] == "physical" and blind_offsets > 0 and offsets.shape[
                    1] == 6:
                t["blind"] = _blind_trial(t, blind_offsets, quiet)
        elif not np.allclose(offsets, t["offsets"]):
            # both variants draw from (seed, protocol, training statistics): a bug if not
            t.setdefault("offset_mismatch", []).append(job.name)

    return after_first


def _evaluate(args, trials: dict, channels) -> list[str]:
    """Every method's :func:`seed_summary` on each trial (``trials[key]["methods"]``) and the
    Figure 2 plots of ``--plot-trials``; returns the plots' paths."""
    plots = []
    for key, t in trials.items():
        methods, states = {}, {}
        for variant, job in t["jobs"].items():
            state, seeds, ev = evaluate_best(job, t["offsets"], args.quiet)
            states[variant] = (state, seeds)
            methods[variant] = {**seed_summary(ev["metrics"], channels),
                                "epochs": job.epochs, "best_epoch": job.summary["best_epoch"],
                                "stopped_early": job.stopped, "run": str(job.run_dir),
                                "best": job.summary["best"]}
            if "mean_offset" not in methods:  # the baselines depend on the data only
                methods["mean_offset"] = seed_summary([ev["baseline_mean_offset"]], channels)
                methods["window_mean"] = seed_summary([ev["baseline_window_mean"]], channels)
        ls = t["least_squares"]
        if "error" not in ls:
            methods["least_squares"] = {**seed_summary([ls["metrics"]], channels),
                                        "interval_s": ls["interval_s"]}
            methods["least_squares_oracle"] = seed_summary([ls["oracle_metrics"]], channels)
        methods.update(t.get("blind", {}))
        t["methods"] = {m: methods[m] for m in METHODS if m in methods}
        if args.plot_trials == "all" or key[2] in args.plot_trials:
            plots.append(str(_figure2(args, key, t, states, channels)))
    return plots


def _aggregate(trials: dict) -> dict:
    """``{experiment: {protocol: {method: mean ± std over trials}}}`` of :data:`HEADLINE`,
    with the trained methods' epochs and best epochs."""
    results: dict = {}
    for (name, protocol, _), t in trials.items():
        per = results.setdefault(name, {}).setdefault(protocol, {})
        for method, rec in t["methods"].items():
            per.setdefault(method, []).append(rec)
    agg: dict = {}
    for name, per_protocol in results.items():
        for protocol, per_method in per_protocol.items():
            for method, recs in per_method.items():
                agg.setdefault(name, {}).setdefault(protocol, {})[method] = {
                    "trials": len(recs), **mean_std_of(recs, HEADLINE),
                    **({"epochs": [r["epochs"] for r in recs],
                        "best_epoch": [r["best_epoch"] for r in recs]}
                       if "epochs" in recs[0] else {})}
    return agg


def main() -> None:
    args, experiments, protocols, n_trials = _arguments()
    budget = Budget(None if args.paper else args.budget)
    enable_compilation_cache()
    extra = [] if args.folds is None else [f"loop.folds={args.folds}"]
    if any(v in VISUAL_VARIANTS for v in args.variants):
        # one window set serves every variant: the rotations ride along unused elsewhere
        extra.append("window.rotations=visual")
    _, _, window = resolve(args, extra, protocol="paper", validation="loo")
    shutil.rmtree(args.out / "runs", ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)

    exp_parts, seq_name, skipped, loaded = _load(args, experiments, window)
    t_data = budget.elapsed()
    log(args.quiet, f"data ready in {t_data:.0f} s: {len(loaded)} sequences, "
                    f"{count_windows(loaded.values())} windows")
    jobs, trials, job_trial, trial_counts = _plan(args, exp_parts, seq_name, protocols, extra,
                                                  n_trials)
    n_plots = sum(1 for (_, _, i) in trials if args.plot_trials == "all" or i in args.plot_trials)
    log(args.quiet, f"{len(jobs)} fits, {n_plots} plots; "
                    f"{'no time limit' if args.paper else f'{budget.left() / 60:.1f} min left'}")
    schedule = train_jobs(jobs, budget, reserve_s=PLOT_RESERVE_S * n_plots + 5.0,
                          quiet=args.quiet,
                          after_first=_first_call(trials, job_trial, args.blind_offsets,
                                                  args.quiet))

    channels = None
    if jobs:
        channels = channel_names(jobs[0].config.model.imu_channels,
                                 jobs[0].config.injection.single_sensor)
    t_eval = time.perf_counter()
    plots = _evaluate(args, trials, channels)
    eval_s = time.perf_counter() - t_eval
    agg = _aggregate(trials)

    rec_budget = budget_record(budget, args.paper)
    settings = _settings(jobs, window, args, n_trials, trial_counts)
    table = _table(agg, trials, settings, rec_budget, schedule, skipped, args)
    (args.out / "table.md").write_text(table)
    write_docs(args, "calib_protocols", table,
               anchor="Avola et al. 2023, Table 4 (real data, the paper column)")
    out_json = {
        "script": "experiments/calib_protocols.py", "argv": sys.argv[1:], **rec_budget,
        "data_s": round(t_data, 1), "eval_s": round(eval_s, 1), "settings": settings,
        "schedule": schedule, "skipped": skipped,
        "paper_table4": {k: {"sign_f1_pct": e.paper[0], "offset_rmse": e.paper[1]}
                         for k, e in EXPERIMENTS.items() if e.paper},
        "mean_std": agg, "trials": _trial_records(trials),
        "plots": plots, "table": str(args.out / "table.md")}
    (args.out / "results.json").write_text(json.dumps(out_json, indent=1, default=_default)
                                           + "\n")
    if not args.quiet:
        print(table)
    print_json({"table": str(args.out / "table.md"), "json": str(args.out / "results.json"),
                "plots": plots, **rec_budget, "target_epochs": schedule["target_epochs"],
                "results": {n: {p: {m: {"trials": s["trials"],
                                        "sign_f1": _m(s["sign_f1"]),
                                        "sign_f1_std": _s(s["sign_f1"]),
                                        "offset_rmse": _m(s["offset_rmse"]),
                                        "offset_rmse_std": _s(s["offset_rmse"])}
                                    for m, s in pm.items()} for p, pm in pp.items()}
                            for n, pp in agg.items()}})


def _trial_records(trials: dict) -> list[dict]:
    """``results.json``'s ``trials``: one record per trial run."""
    return [{"experiment": n, "protocol": p, "trial": i, "held_out": t["held_out"],
             "train_windows": t["train_windows"], "val_windows": t["val_windows"],
             "offsets": t["offsets"].tolist(), "methods": t["methods"],
             "offset_mismatch": t.get("offset_mismatch"),
             "least_squares_error": t["least_squares"].get("error"),
             "least_squares_s": t.get("least_squares_s"),
             "figure2_check": t.get("figure2_check")}
            for (n, p, i), t in trials.items()]


def _m(stat):
    return None if stat is None else round(stat["mean"], 5)


def _s(stat):
    return None if stat is None else round(stat["std"], 5)


def _default(value):
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _figure2(args, key, t: dict, states: dict, channels) -> Path:
    """The trial's best models predict every held-out window with the first of the K offsets
    injected (:func:`~uavcal_jax.calib.predict.predict_sequence`, the frame-token reuse
    path), plotted against least squares and the truth; the predictions' offset RMSE is
    checked against :func:`~uavcal_jax.calib.loop.evaluate`'s on that offset."""
    name, protocol, i = key
    offset = t["offsets"][0]
    lines, start_s, check = {}, None, {}
    val = t["val"]
    for variant, (state, seeds) in states.items():
        preds = [predict_sequence(state, p.windows.subset(p.indices), seeds,
                                  inject_offset=offset) for p in val]
        lines[variant] = np.concatenate([p.per_window for p in preds])
        start_s = np.concatenate([p.start_s for p in preds])
        ev = evaluate(state, val, seeds, offsets=offset[None])
        check[variant] = {"predict_offset_rmse": float(np.sqrt(np.mean(np.square(
                              lines[variant] - offset)))),
                          "evaluate_offset_rmse": float(np.mean([m["offset_rmse"]
                                                                 for m in ev["metrics"]])),
                          "seeds": seeds}
    ls = t["least_squares"]
    if "error" not in ls:
        lines["least_squares"] = ls["per_window"]
        lines["least_squares_oracle"] = ls["oracle_per_window"]
    lines["mean_offset"] = np.broadcast_to(t["mean_offset_value"],
                                           next(iter(lines.values())).shape)
    t["figure2_check"] = check
    title = (f"{EXPERIMENTS[name].label}, {protocol} protocol, trial {i}: held out "
             f"{', '.join(t['held_out'])}; offset 1 of {len(t['offsets'])}")
    path = args.out / f"fig2_{name}_{protocol}_{TRIAL_FORMAT.format(i)}.png"
    return plot_offsets(path, start_s, channels, {METHODS[k]: v for k, v in lines.items()},
                        true=offset, true_label="true (injected)", title=title,
                        styles={METHODS[k]: FIGURE2_STYLES[k] for k in lines})


def _settings(jobs, window, args, n_trials, trial_counts) -> dict:
    if not jobs:
        return {"sets": args.set}
    train, _ = jobs[0].data()
    T = train[0].windows.frames_per_window
    return {"preset": "paper" if args.paper else "small", "sets": args.set,
            "frames_per_window": T, "max_duration_s": args.max_duration,
            "sequences": args.sequences, "trials": n_trials, "trials_of": trial_counts,
            "val_offsets": jobs[0].loop.val_offsets,
            "describe": describe(jobs[0].config, window, T),
            "seed": args.seed, "trial_seeds": args.trial_seeds,
            "max_epochs": jobs[0].config.train.epochs}


def _epochs(stat: dict) -> str:
    lo, hi = min(stat["epochs"]), max(stat["epochs"])
    blo, bhi = min(stat["best_epoch"]), max(stat["best_epoch"])
    return (f"{lo}" if lo == hi else f"{lo}-{hi}") + (
        f" ({blo})" if blo == bhi else f" ({blo}-{bhi})")


def _paired_lines(trials: dict) -> list[str]:
    """Lines of the closed-form heads' offset RMSE minus the window mean's on the same trial
    (mean ± std over the trials): the check that the head improves on where it starts."""
    diffs: dict = {}
    for (name, protocol, _), t in trials.items():
        base = t["methods"].get("window_mean")
        for variant in ("closed_form", "motion_tokens", "motion_tilt"):
            if base is not None and variant in t["methods"]:
                diffs.setdefault((name, protocol, variant), []).append(
                    t["methods"][variant]["offset_rmse"] - base["offset_rmse"])
    if not diffs:
        return []
    lines = ["Closed-form heads against the window mean, paired by trial (offset RMSE "
             "difference, negative: the head is better; mean ± std over trials):", ""]
    for (name, protocol, variant), d in diffs.items():
        lines.append(f"- {EXPERIMENTS[name].label}, {protocol}: {METHODS[variant]} "
                     f"{np.mean(d):+.4f} ± {np.std(d):.4f} ({len(d)} trials)")
    return lines + [""]


def _table(agg, trials, settings, rec_budget, schedule, skipped, args) -> str:
    seqs: dict = {}
    for (name, _, i), t in trials.items():
        seqs.setdefault(name, {})[i] = ", ".join(t["held_out"])
    k_offsets = settings.get("val_offsets")

    def trial_line(name, held):
        kind = "fold" if EXPERIMENTS[name].validation == "kfold" else "held out"
        return (f"{name}: {len(held)} of {settings['trials_of'][name]} trials ("
                + "; ".join(f"{TRIAL_FORMAT.format(i)} {kind} "
                            f"{'' if kind == 'held out' else f'{i} of '}{s}"
                            for i, s in sorted(held.items())) + ")")

    lines = ["# Calibrator validation protocols (Table 4 analogue)", "",
             f"- {mode_line(rec_budget, schedule, settings.get('max_epochs'), 'every fit')}.",
             f"- Model and windows: {settings.get('describe', '-')}.",
             "- Data: simulated sequences (`uavcal_jax.sim.training_sets`, 376x240 renders of the "
             "trajectories in ../shared/data/trajectories), "
             + ("whole trajectories" if args.max_duration is None else
                f"each capped at {args.max_duration:g} s") + ".",
             "- Trials: " + "; ".join(trial_line(n, h) for n, h in seqs.items()) + ".",
             f"- Every method on the same validation windows, each window evaluated once per "
             f"offset with the same {k_offsets} offsets, each shared by every window of the trial, "
             "drawn by the protocol from "
             + (f"`train.seed = {args.seed} + trial`" if args.trial_seeds else
                f"`train.seed = {args.seed}` (every trial; the paper protocol's also from the "
                "trial's training statistics)")
             + "; metrics pooled over the offsets, then mean ± std over trials. Offset RMSE "
             "pools gyro (rad/s) and accel (m/s^2), as the paper; the per-sensor RMSEs beside. "
             "Epochs: trained (best), over the trials.",
             "- Window mean: each window's mean IMU sample minus the training set's (no "
             "learning). Least squares estimates the stream's whole constant error (the "
             "injected offset plus the simulated IMU's turn-on bias); the oracle row subtracts "
             "the true bias.",
             "- Paper values: Table 4 of Avola et al. 2023 (real EuRoC / UZH-FPV, their "
             "protocol, one offset per trial); ours are on simulated data.", ""]
    if skipped:
        lines += [f"- Skipped: {k}: {v}" for k, v in skipped.items()] + [""]
    lines += _paired_lines(trials)
    lines += ["| experiment | protocol | method | trials | epochs | sign F1 (%) | offset RMSE | "
              "gyro RMSE (rad/s) | accel RMSE (m/s^2) | paper sign F1 (%) | "
              "paper offset RMSE |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, per_protocol in agg.items():
        for protocol, per_method in per_protocol.items():
            for method, s in per_method.items():
                ref = EXPERIMENTS[name].paper if (method == "transformer"
                                                  and protocol == "paper") else None
                lines.append(
                    f"| {EXPERIMENTS[name].label} | {protocol} | {METHODS[method]} | "
                    f"{s['trials']} | {_epochs(s) if 'epochs' in s else '-'} | "
                    f"{fmt_mean_std(s['sign_f1'], 100, 2)} | "
                    f"{fmt_mean_std(s['offset_rmse'])} | {fmt_mean_std(s['gyro_rmse'])} | "
                    f"{fmt_mean_std(s['accel_rmse'])} | "
                    f"{'-' if ref is None else f'{ref[0]:.2f}'} | "
                    f"{'-' if ref is None else f'{ref[1]:.3f}'} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
