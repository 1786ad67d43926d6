"""``uavcal calib``: train and evaluate the transformer IMU self-calibrator (Avola et al. 2023).

Every option's default and choices come from the configuration dataclasses (the root
:class:`uavcal_jax.calib.config.CalibRunConfig`); ``--set`` reaches every field of it, in
``train``, ``eval`` and ``predict``. Each writes the configuration it ran with beside its
results, with its other inputs under ``"command"``: ``RUN/config.json`` (train),
``eval_config.json`` (eval, in each evaluated folder, or under ``--out``; never into the
package's shipped weights, :func:`uavcal_jax.runs.results_folder`), ``OUT.config.json`` beside
``predict --out``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from uavcal_jax.argtypes import parse_offset, positive_int, print_json
from uavcal_jax.errors import DataError
from uavcal_jax.xla_cache import enable_compilation_cache

DESCRIPTION = """\
Train and evaluate the transformer IMU self-calibrator of Avola et al. (Sensors 2023): windows
of camera frames and IMU samples, a constant offset injected into the IMU, the network learns to
predict it. DIR: EuRoC folders (real or simulated by `uavcal simulate`) or folders of them.
Bad input: a sequence shorter than one window is an error; NaN/inf IMU rows are dropped with a
warning; all-black frames are treated as missing frames (masked) with a warning."""

TRAIN_EPILOG = """\
--set KEY=VALUE sets any field: model.*, loss.*, injection.*, train.* (uavcal_jax.calib.config),
window.* (duration, stride, size WxH, camera, color, min_valid_fraction) and loop.* (monitor
train|val, keep, validation, val_fraction, split_seed, folds); --set wins over the flags, the
flags over the preset (a flag left out keeps the preset's value). RUN gets config.json (the
resolved configuration), data.json (the windows of each side), metrics.jsonl and
checkpoints/{last,best}; loo/kfold write one such folder per trial, RUN/trial_NN, and
RUN/result.json with the mean and standard deviation of the validation metrics over trials.

presets (--preset): paper = Table 2 of the paper, the defaults (d 256, 320x180 frames in
64x64 patches, 10 s windows at 20 Hz, AdamW 1e-5: days on a CPU); small = minutes on a CPU
(160x96 frames in 32x32 patches at 10 Hz, d 64, pre-norm layers, AdamW 1e-3, the loss in each
channel's offset units); shipped = the weights shipped in the package (small with the physical
protocol, 2 s windows every 0.5 s at 20 Hz, patience 6 on the validation loss). Their settings
are in uavcal_jax/calib/presets.py (PRESETS).

examples:
  uavcal calib train --data sims/ --out runs/cal --validation loo --preset small --epochs 40
  uavcal calib train --data sims/ --out runs/cal --validation loo --epochs 20
  uavcal calib train --data sims/V1_01 --out runs/cal --seeds 4 --set window.duration=4
  uavcal calib train --data sims/ --out runs/cal --validation loo --resume"""

PREDICT_DESCRIPTION = """\
Estimate the constant offset in a recording's IMU (what to subtract: gyro rad/s, accel m/s^2).
--method vio-bias (the default, measured the most accurate: errors within 1e-4 rad/s and 1e-2
m/s^2 on a 40 s simulated flight, the shipped transformer's up to 0.03 and 0.11) runs the
stereo VIO and takes the median of its bias states over the tracked frames of the last two
thirds of the flight; --method transformer cuts the recording into a trained calibrator's
windows and takes the median of its per-window estimates; --method auto runs several methods
(--set methods=vio-bias,visual-ls,transformer, the default) and fuses them per channel by
inverse variance, skipping one that fails. Every method gives `sigma`, the standard deviation
of its estimate's error, its items' correlation over the flight accounted for (a transformer
only when trained with model.variance, as the shipped weights are); a channel the recording
does not determine (a flight that hardly turns, for the accelerometer across gravity) shows a
large one. No method sees the ground truth. Each is scored afterwards
against its label: vio-bias estimates the total constant error (the offsets known to be in the
IMU plus the sensor's own bias, the mean of the ground truth's bias columns), a transformer
what its run was trained on (injection.label). The offsets are known when the recording is a
simulated one made with `uavcal simulate --imu-offset` (sim_config.json) and/or --inject adds
one; then the error is printed too. With --out, the configuration it ran with goes to
OUT.config.json (e.g. offsets.config.json)."""

PREDICT_EPILOG = """\
methods:
{methods}

examples:
  uavcal calib predict --sequence sims/V1_01 --out offsets.json --plot offsets.png
  uavcal calib predict --sequence sims/V1_01 --set tail_fraction=0.5 vio.solver.max_iterations=4
  uavcal calib predict --method transformer --checkpoint runs/cal --sequence data/V1_01 \\
      --inject 0.02,0,0,0.1,0,0
  uavcal calib predict --method auto --sequence sims/V1_01 --json
  uavcal vio --sequence sims/V1_01 --out traj.txt --offsets offsets.json"""


def predict_epilog() -> str:
    """:data:`PREDICT_EPILOG` with the registered methods listed."""
    import textwrap

    from uavcal_jax.pipeline.offset_estimators import METHODS

    methods = "\n".join(textwrap.fill(f"{m.name}: {m.summary}", 96, initial_indent="  ",
                                       subsequent_indent="    ") for m in METHODS.values())
    return PREDICT_EPILOG.format(methods=methods)


#: ``calib eval``'s record of the configuration it evaluated with, in each evaluated folder.
EVAL_CONFIG_FILE = "eval_config.json"
#: Headline validation metrics averaged over trials.
HEADLINE = ("val_loss", "val_offset_rmse", "val_sign_f1", "baseline_offset_rmse",
            "window_mean_offset_rmse")


def register(subparsers) -> None:
    from uavcal_jax.calib.config import (
        FRAME_ENCODER_DTYPES,
        PROTOCOLS,
        VALIDATIONS,
        InjectionConfig,
        LoopConfig,
        TrainConfig,
    )
    from uavcal_jax.calib.presets import PRESETS
    from uavcal_jax.pipeline.offset_estimators import DEFAULT_METHOD, method_names
    from uavcal_jax.runs import EVAL_HOME, KINDS

    raw = argparse.RawDescriptionHelpFormatter
    parser = subparsers.add_parser("calib", help="train and evaluate the IMU self-calibrator",
                                   description=DESCRIPTION, formatter_class=raw)
    sub = parser.add_subparsers(dest="calib_command", metavar="ACTION", required=True)

    p = sub.add_parser("train", help="train the calibrator on EuRoC folders",
                       description=DESCRIPTION, epilog=TRAIN_EPILOG, formatter_class=raw)
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="EuRoC sequence folders or folders of them")
    p.add_argument("--out", required=True, metavar="RUN", help="the run folder to write")
    p.add_argument("--preset", choices=tuple(PRESETS), default="paper",
                   help="starting configuration, see below; --set and the other flags win "
                        "[default: %(default)s]")
    p.add_argument("--protocol", choices=PROTOCOLS, default=InjectionConfig.protocol,
                   action=_Given,
                   help="offset injection protocol, injection.protocol (paper: N(mu, n_m "
                        "sigma^2) of the training IMU; symmetric: U(-n_m sigma, n_m sigma); "
                        "physical: real bias ranges) [default: the preset's; paper's: "
                        "%(default)s]")
    p.add_argument("--validation", choices=VALIDATIONS, default=LoopConfig.validation,
                   action=_Given,
                   help="validation scheme, loop.validation (split: fixed random split over "
                        "windows; loo: leave one sequence out; kfold: contiguous blocks of "
                        "windows) [default: the preset's; paper's: %(default)s]")
    p.add_argument("--seeds", type=positive_int, default=TrainConfig.seeds, action=_Given,
                   help="models trained at once, vmapped, train.seeds [default: the "
                        "preset's; paper's: %(default)s]")
    p.add_argument("--epochs", type=positive_int, default=TrainConfig.epochs, action=_Given,
                   help="most epochs (early stopping may end sooner), train.epochs "
                        "[default: the preset's; paper's: %(default)s]")
    _add_set(p)
    p.add_argument("--resume", action="store_true",
                   help="continue RUN from its last checkpoints (same settings; --epochs may "
                        "be raised)")
    p.add_argument("--stop-after", type=positive_int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_train)

    p = sub.add_parser("eval", help="metrics of a trained run's best model",
                       description="Evaluate the best checkpoint of a run (each trial of a "
                       "loo/kfold run) on its validation windows or on --data, beside the "
                       "mean-offset baseline.", formatter_class=raw)
    p.add_argument("run", metavar="RUN", help="a run folder written by `calib train`")
    p.add_argument("--data", nargs="+", metavar="DIR", default=None,
                   help="evaluate on every window of these sequences [default: the run's "
                        "validation windows]")
    p.add_argument("--offsets", type=positive_int, default=None, metavar="K",
                   help="evaluate once per offset, K offsets drawn by the run's injection "
                        "protocol, each shared by every window, loop.val_offsets [default: the "
                        "run's]")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="write eval_config.json here (a loo/kfold run's under DIR/trial_NN) "
                        f"[default: RUN; ./{EVAL_HOME}/<RUN's name> when RUN is the shipped "
                        "weights or not writable]")
    _add_set(p, "the run's configuration (what a restored model may change: run control, "
                "batch size, window stride; see calib.loop.INFERENCE_KEYS)")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_eval)

    p = sub.add_parser("predict", help="estimate a recording's IMU offset (VIO bias or a "
                                       "trained model)",
                       description=PREDICT_DESCRIPTION, epilog=predict_epilog(),
                       formatter_class=raw)
    p.add_argument("--sequence", required=True, metavar="DIR",
                   help="an EuRoC folder (real, or simulated by `uavcal simulate`) or a ROS bag")
    p.add_argument("--method", default=DEFAULT_METHOD, metavar="NAME",
                   help=f"the estimator, one of {', '.join(method_names())} (below) "
                        f"[default: %(default)s, the most accurate measured]")
    p.add_argument("--checkpoint", metavar="RUN", default=None,
                   help="transformer: a run folder written by `calib train` (a loo/kfold "
                        "trial folder, RUN/trial_NN) [default: the small weights shipped in "
                        "the package, made by experiments/calib_default_weights.py]")
    p.add_argument("--kind", choices=KINDS, default=None,
                   help="transformer: which checkpoint of the run [default: best]")
    p.add_argument("--inject", type=parse_offset, default=None, metavar="GX,GY,GZ,AX,AY,AZ",
                   help="add this constant offset to the recorded IMU first (try a method on "
                        "a clean recording with a known miscalibration; write --inject=-0.01,"
                        "... for a negative first value)")
    p.add_argument("--out", type=Path, default=None, metavar="JSON",
                   help='write the estimate as {"offset": [6 numbers], ...}, the input of '
                        "`uavcal vio --offsets`; the configuration it ran with goes to "
                        "JSON's name with .config.json")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="write a PNG of the per-window (per-frame) estimates against the true "
                        "offset")
    p.add_argument("--frame-dtype", choices=FRAME_ENCODER_DTYPES, default=None,
                   help="transformer: operand type of the frame encoder's matrix products: "
                        "bfloat16 halves their time on CPUs with bfloat16 dot products "
                        "(float32 sums; see ModelConfig.frame_encoder_dtype) [default: the "
                        "run's]")
    _add_set(p, "the method's options: vio-bias: tail_fraction and vio.* (the VioConfig of "
                "`uavcal vio`, e.g. vio.solver.max_iterations=4); transformer: the run's "
                "configuration (what a restored model may change: e.g. window.stride; see "
                "calib.loop.INFERENCE_KEYS)")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bars")
    p.set_defaults(func=run_predict)


# ----------------------------------------------------------------------------- configuration


class _Given(argparse.Action):
    """Store the value and note the flag as given (``args.given``): a flag left out keeps the
    preset's value, not its parser default (the paper preset's)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.given = {*getattr(namespace, "given", ()), self.dest}


def _add_set(p, what: str = "configuration fields (see below)") -> None:
    p.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                   help=f"set {what}; repeatable; an unknown key is an error naming it")


def _inputs(args, *names: str) -> dict:
    """The command's inputs besides the configuration (``"command"`` of its config file):
    the action and the arguments ``names``, paths as strings."""
    def plain(value):
        if isinstance(value, list | tuple):
            return [plain(v) for v in value]
        return str(value) if isinstance(value, Path) else value

    return {"action": f"calib {args.calib_command}",
            **{name: plain(getattr(args, name)) for name in names}}


def train_configs(args):
    """The :class:`~uavcal_jax.calib.config.CalibRunConfig` of parsed ``calib train``
    arguments: the preset, the flags given, then ``--set``."""
    from uavcal_jax.calib.presets import resolve_configs

    given = getattr(args, "given", ())
    return resolve_configs(args.set, preset=args.preset, **{
        name: getattr(args, name) for name in ("protocol", "validation", "seeds", "epochs")
        if name in given})


# ----------------------------------------------------------------------------- train


def _aggregate(rows: list[dict]) -> dict:
    from uavcal_jax.calib.trials import mean_std_of

    return {k: v for k, v in mean_std_of(rows, HEADLINE).items() if v is not None}


def _sources(window) -> dict:
    """The motion sources ``load_windows`` needs for ``window`` (the VIO front end's camera
    rotations, its poses: cached beside each recording)."""
    from uavcal_jax.pipeline.motion_inputs import folder_sources
    return folder_sources(window)


def run_train(args) -> int:
    from uavcal_jax.calib.data import load_windows
    from uavcal_jax.calib.trials import run_trials, validation_trials
    from uavcal_jax.data.calib_result import write_calib_result

    run = train_configs(args)
    enable_compilation_cache()
    parts = load_windows(args.data, run.window, **_sources(run.window))
    out = Path(args.out)
    results = run_trials(run.calib, run.loop, validation_trials(parts, run.loop), out,
                         resume=args.resume, progress=not args.json,
                         stop_after=args.stop_after,
                         inputs=_inputs(args, "data", "out", "preset", "set", "resume"))
    summary = write_calib_result(out, validation=run.loop.validation,
                                 protocol=run.injection.protocol, seeds=run.train.seeds,
                                 trials=results, mean_std=_aggregate([r["best"] for r in results]))
    if args.json:
        print_json(summary)
    else:
        for r in results:
            b = r["best"]
            nan = float("nan")
            print(f"{r['run']}: {r['epochs']} epochs, best {r['best_epoch']}: loss "
                  f"{b.get('loss', nan):.4f}, val offset RMSE {b.get('val_offset_rmse', nan):.4f}"
                  f" (baselines: mean offset {b.get('baseline_offset_rmse', nan):.4f}, window "
                  f"mean {b.get('window_mean_offset_rmse', nan):.4f})")
        _print_mean_std(summary["mean_std"], len(results))
    return 0


def _print_mean_std(agg: dict, trials: int) -> None:
    if trials > 1:
        print("mean ± std over trials: " + ", ".join(
            f"{k} {agg[k]['mean']:.4f} ± {agg[k]['std']:.4f}" for k in HEADLINE if k in agg))


# ----------------------------------------------------------------------------- eval


def run_eval(args) -> int:
    from uavcal_jax.calib.data import load_windows
    from uavcal_jax.calib.loop import evaluate, read_run_config, restore_run
    from uavcal_jax.calib.presets import resolve_configs
    from uavcal_jax.calib.trials import trial_dirs, validation_windows
    from uavcal_jax.config import write_config
    from uavcal_jax.runs import results_folder, results_redirect

    enable_compilation_cache()
    cache: dict = {}
    trials = []
    folder = results_folder(args.run, args.out)
    for run_dir in trial_dirs(args.run):
        run = resolve_configs(args.set, preset=read_run_config(run_dir),
                              arguments={"loop.val_offsets": args.offsets})
        parts = (load_windows(args.data, run.window, **_sources(run.window))
                 if args.data
                 else validation_windows(run_dir, run.window, cache))
        if not parts:
            raise DataError("no validation windows to evaluate on: give --data", run_dir)
        state, seeds = restore_run(run_dir, parts, run=run)
        res = evaluate(state, parts, seeds, draws=run.loop.val_offsets, show=not args.json)
        # a trial's results go to the same place under the results folder as it is in RUN
        trial_out = folder / run_dir.relative_to(args.run)
        config = write_config(trial_out / EVAL_CONFIG_FILE, run,
                              command=_inputs(args, "run", "data", "offsets", "out", "set"))
        trials.append({"run": str(run_dir), "config": str(config), **res})
    why = results_redirect(args.run) if args.out is None else None
    if why is not None:
        print(f"{args.run} {why}: the evaluation went to {folder} (--out DIR chooses)",
              file=sys.stderr, flush=True)
    rows = [{"val_loss": float(np.mean(t["loss"])),
             "val_offset_rmse": float(np.mean([m["offset_rmse"] for m in t["metrics"]])),
             "val_sign_f1": float(np.mean([m["sign_f1"] for m in t["metrics"]])),
             "baseline_offset_rmse": t["baseline_mean_offset"]["offset_rmse"],
             "window_mean_offset_rmse": t["baseline_window_mean"]["offset_rmse"]}
            for t in trials]
    summary = {"run": str(args.run), "data": args.data, "trials": trials,
               "mean_std": _aggregate(rows)}
    if args.json:
        print_json(summary)
    else:
        for t, r in zip(trials, rows, strict=True):
            print(f"{t['run']}: {t['windows']} windows x {len(t['offsets'])} offsets, offset "
                  f"RMSE {r['val_offset_rmse']:.4f}, sign F1 {r['val_sign_f1']:.4f}; baselines "
                  f"(offset RMSE): mean offset {r['baseline_offset_rmse']:.4f}, window mean "
                  f"{r['window_mean_offset_rmse']:.4f}")
        _print_mean_std(summary["mean_std"], len(rows))
    return 0


# ----------------------------------------------------------------------------- predict


def _offset_table(channels, rows: dict[str, np.ndarray]) -> str:
    lines = [f"{'':>16}" + "".join(f"{c:>10}" for c in channels)]
    lines += [f"{name:>16}" + "".join(f"{v:>10.4f}" for v in values)
              for name, values in rows.items()]
    return "\n".join(lines + ["(gyro rad/s, accel m/s^2)"])


def _headline(summary: dict) -> str:
    if summary["method"] == "transformer":
        seeds = summary["seeds"]
        return (f"transformer {summary['run']} ({summary['kind']}, {seeds} "
                f"seed{'s' * (seeds > 1)}): {summary['windows']} windows of "
                f"{summary['window_s']:g} s on {summary['sequence']}")
    if summary["method"] == "vio-bias":
        return (f"vio-bias: median VIO bias over {summary['frames_used']} of "
                f"{summary['frames']} frames ({summary['resets']} resets) on "
                f"{summary['sequence']}")
    return f"{summary['method']}: {summary['items']} {summary['item']}s on {summary['sequence']}"


def run_predict(args) -> int:
    from uavcal_jax.config import write_config
    from uavcal_jax.data.offset_json import write_offset_json
    from uavcal_jax.data.read import read_sequence
    from uavcal_jax.data.sim_config import recorded_imu_offset
    from uavcal_jax.pipeline.offset_estimators import configure_method
    from uavcal_jax.pipeline.predict_offset import known_offset, predict_offset, score

    enable_compilation_cache()
    options = configure_method(args.method, args.set, checkpoint=args.checkpoint,
                               kind=args.kind, frame_dtype=args.frame_dtype)
    sequence, _ = read_sequence(args.sequence)
    summary, estimate = predict_offset(sequence, args.method, options,
                                       inject=args.inject, progress=not args.json)
    # the truth, only now: the simulator's record and the ground truth
    recorded = recorded_imu_offset(args.sequence)
    summary.update(sequence=str(args.sequence),
                   recorded=None if recorded is None else recorded.tolist(),
                   **score(estimate, known_offset(recorded, args.inject),
                           sequence.ground_truth))
    true = None if summary["true"] is None else np.asarray(summary["true"])
    if args.out is not None:
        if len(estimate.channels) != 6:
            warnings.warn(f"{'/'.join(estimate.channels)} estimated: the other channels are "
                          "written as 0 in " + str(args.out), stacklevel=1)
        write_offset_json(args.out, estimate.offset,
                          **{k: summary[k] for k in ("method", "label", "run", "sequence",
                                                     "channels", "windows", "items",
                                                     "per_window", "true", "error")
                             if k in summary})
        summary["out"] = str(args.out)
        command = _inputs(args, "method", "sequence", "kind", "inject", "out", "plot", "set")
        if "run" in summary:
            command["checkpoint"] = summary["run"]
        summary["config"] = str(write_config(args.out.with_suffix(".config.json"),
                                             estimate.settings, command=command))
    if args.plot is not None:
        from uavcal_jax.plots import plot_offsets

        summary["plot"] = str(plot_offsets(
            args.plot, estimate.item_t_s, estimate.channels, {estimate.item: estimate.per_item},
            true=true, median=estimate.median, title=f"{args.method} on {args.sequence}"))
    if args.json:
        print_json(summary)
        return 0
    rows = {"estimate (median)": estimate.median,
            f"{estimate.item} spread": np.asarray(summary["per_window_std"])}
    if summary.get("sigma") is not None:  # null: a channel the method did not determine
        rows["sigma"] = np.array([np.inf if v is None else v for v in summary["sigma"]])
    for name, part in summary.get("methods", {}).items():  # auto: what it fused
        if "offset" in part:
            rows[name] = np.array([part["offset"][part["channels"].index(c)]
                                   if c in part["channels"] else np.nan
                                   for c in estimate.channels])
    if true is not None:
        rows.update({f"true ({summary['label']})": true, "error": np.asarray(summary["error"])})
    print(_headline(summary))
    print(_offset_table(estimate.channels, rows))
    for key in ("out", "config", "plot"):
        if key in summary:
            print(f"wrote {summary[key]}")
    return 0
