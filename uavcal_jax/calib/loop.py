"""The calibrator's training loop: epochs, K vmapped seeds, early stopping, checkpoints,
exact resume. The numerics are the pure steps of :mod:`uavcal_jax.calib.train`; the run
folder, checkpoints, resume and the epoch loop are :mod:`uavcal_jax.runs`; this module gives that
loop the calibrator's data, steps, metrics and validation.

Randomness is explicit and derived from ``(train.seed, purpose, ...)`` only, so a resumed run
draws what the uninterrupted one drew: the epoch's window order from ``(seed, epoch)``, the
step key of seed ``k`` (offsets and dropout) from ``(seed, k, global step)``, the inits from
``(seed, k)``, the validation set's one offset from ``seed``.

Run folder ``run_dir`` (:mod:`uavcal_jax.runs`): ``config.json`` (the resolved
:class:`~uavcal_jax.calib.config.CalibRunConfig`, its frames per window and frame shape, and the
caller's other inputs; :func:`read_run_config`), ``metrics.jsonl`` (one JSON row per epoch:
training loss per seed and their mean, validation loss and eq. 19-23 metrics, time) and
``checkpoints/{last,best}``, each holding ``{"state": CalibState, "key": key_data}``.

Early stopping (section 4.4): after ``train.patience`` epochs without improvement of the
monitored loss (``loop.monitor``: the epoch's training loss, the paper, or the
validation loss), the mean over seeds. ``best`` is the epoch of the lowest monitored loss.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.calib.baselines import mean_offset
from uavcal_jax.calib.config import (
    RUN_EXTRAS,
    CalibConfig,
    CalibRunConfig,
    LoopConfig,
    run_layout,
)
from uavcal_jax.calib.data import (
    Windows,
    as_windows,
    gather,
    mean_sensor_bias,
    training_statistics,
)
from uavcal_jax.calib.inject import ImuStats, training_offsets, validation_offsets
from uavcal_jax.calib.metrics import calibration_metrics, metrics_from_sums
from uavcal_jax.calib.model import without_correction
from uavcal_jax.calib.train import (
    CalibState,
    create_train_state,
    create_train_states,
    eval_step,
    eval_step_seeds,
    train_step,
    train_step_seeds,
)
from uavcal_jax.config import apply_overrides, from_dict, to_dict
from uavcal_jax.errors import DataError
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.runs import (
    CONFIG_FILE,
    Checkpoints,
    Loop,
    RunSpec,
    Selection,
    train_epochs,
    write_folder,
)

__all__ = ["INFERENCE_KEYS", "RESUMABLE_KEYS", "FitResult", "epoch_order", "evaluate",
           "first_seed",
           "export_weights", "fit", "mean_offset_baseline", "read_run_config",
           "resolved_config", "restore_run", "validation_draws"]

#: Configuration keys a resumed or restored checkpoint may differ in: the epoch budget (a
#: resumed run may train longer), the frame encoder's operand type (a numerics choice: the
#: parameters mean the same under either; checkpoints written before the field existed lack
#: it) and the frame-decoding threads (checkpoints written before the run config root lack
#: them).
RESUMABLE_KEYS = frozenset({"train.epochs", "model.frame_encoder_dtype", "window.workers"})
#: Settings in which a model restored to evaluate or predict (:func:`restore_run`) may differ
#: from its checkpoint, besides ``RESUMABLE_KEYS``: what is done with the model, not what it
#: is (run control, the batch size, where windows start, how many real frames one needs).
INFERENCE_KEYS = RESUMABLE_KEYS | {f"loop.{f.name}" for f in fields(LoopConfig)} | {
    "train.batch_size", "window.stride", "window.min_valid_fraction"}
# Purposes folded into the base key (one stream each).
_INIT, _STEP, _ORDER, _VAL, _BASELINE = range(5)
#: Offsets drawn to estimate the training distribution's mean (the mean-offset baseline).
BASELINE_DRAWS = 4096


@dataclass
class FitResult:
    """``state``: the final :class:`CalibState` (stacked on a leading ``K`` axis when
    ``seeds > 1``); ``summary``: a JSON-ready dict of the run."""

    state: CalibState
    summary: dict


def _window_shape(windows: list[Windows]) -> dict:
    ws = windows[0].windows
    return {"frames_per_window": ws.frames_per_window, "frame_shape": list(ws.frames.shape[1:])}


def resolved_config(run: CalibRunConfig, windows: list[Windows]) -> dict:
    """What ``config.json`` records (besides the caller's inputs) and a checkpoint must match
    to be restored: the root's :func:`~uavcal_jax.config.to_dict` and the frames per window
    and frame shape of ``windows`` (cut with ``run.window``)."""
    return {**to_dict(run), **_window_shape(windows)}


def _root(config: CalibConfig) -> jax.Array:
    return jax.random.key(config.train.seed)


def _step_keys(root: jax.Array, seeds: int, step: int) -> jax.Array:
    base = jax.random.fold_in(root, _STEP)
    keys = jnp.stack([jax.random.fold_in(jax.random.fold_in(base, k), step)
                      for k in range(seeds)])
    return keys[0] if seeds == 1 else keys


def epoch_order(root: jax.Array, epoch: int, n: int) -> np.ndarray:
    """The window order of ``epoch``: a permutation of ``n`` from ``(seed, epoch)``."""
    key = jax.random.fold_in(jax.random.fold_in(root, _ORDER), epoch)
    return np.asarray(jax.random.permutation(key, n))


def first_seed(state: CalibState, seeds: int) -> CalibState:
    """The first seed's state of a vmapped ``state`` (``seeds > 1``), else ``state``: what
    every seed shares (configuration, training statistics) is read from it."""
    return jax.tree.map(lambda x: x[0], state) if seeds > 1 else state


def mean_offset_baseline(state: CalibState, seeds: int) -> jax.Array:
    """The mean-offset baseline ``(C,)``: the mean of :data:`BASELINE_DRAWS` training offsets
    drawn by the run's protocol from its training statistics (the first seed's: all seeds
    share them)."""
    s = first_seed(state, seeds)
    key = jax.random.fold_in(_root(s.config), _BASELINE)
    return mean_offset(training_offsets(key, s.config.injection, s.imu_stats, BASELINE_DRAWS))


def _init_state(config: CalibConfig, parts: list[Windows], stats: ImuStats, seeds: int,
                abstract: bool = False):
    # the labels are not part of the state's shapes: a recording without ground truth restores
    sample = gather(parts, np.arange(1), config.model, config.injection.single_sensor,
                    tilt=False)
    keys = jax.random.split(jax.random.fold_in(_root(config), _INIT), seeds)
    if not abstract:
        return (create_train_state(config, keys[0], sample, stats) if seeds == 1 else
                create_train_states(config, keys, sample, stats))
    # K stacked states: one state's shapes with a leading K axis (create_train_states
    # iterates over its keys, which eval_shape cannot trace)
    one = jax.eval_shape(lambda: create_train_state(config, keys[0], sample, stats))
    return one if seeds == 1 else jax.tree.map(
        lambda s: jax.ShapeDtypeStruct((seeds, *s.shape), s.dtype), one)


def _window_means(batch: dict) -> np.ndarray:
    """Masked mean over each window's samples of the clean IMU, ``(B, C)``."""
    mask = np.asarray(batch["mask"], np.float64)[..., None]
    return (np.asarray(batch["imu"], np.float64) * mask).sum(1) / np.maximum(mask.sum(1), 1.0)


def validation_draws(state: CalibState, seeds: int, draws: int) -> np.ndarray:
    """``(draws, C)`` validation offsets drawn from ``(seed, "val")`` by the run's protocol
    and training statistics (the first seed's: all seeds share them)."""
    s0 = first_seed(state, seeds)
    key = jax.random.fold_in(_root(s0.config), _VAL)
    if draws == 1:  # the paper's one offset of a trial
        return np.asarray(validation_offsets(key, s0.config.injection, s0.imu_stats, 1))
    return np.asarray(training_offsets(key, s0.config.injection, s0.imu_stats, draws))


def evaluate(state: CalibState, parts: list[Windows], seeds: int, *,
             offsets: np.ndarray | None = None, draws: int = 1, show: bool = False,
             label_bias: np.ndarray | None = None) -> dict:
    """Validation of ``state`` on ``parts``, once per offset: each pass injects one offset into
    every window (the paper's one offset per trial) and the metrics pool the passes.

    Args:
        offsets: ``(K, C)`` or ``(C,)``; default ``draws`` offsets from
            :func:`validation_draws`.
        draws: passes when ``offsets`` is not given (1: the paper; more average the trial's
            luck of the draw out of its figures).
        label_bias: ``(C,)`` under the ``total`` label, the training windows' mean sensor
            bias (:func:`uavcal_jax.calib.data.mean_sensor_bias`): the baselines add it, as a
            no-learning estimate would; ``None``: they predict the offset part alone.

    Returns ``loss`` (per seed list when ``seeds > 1``), the eq. 19-23 metrics per seed
    (overall and per channel), those of two baselines on the same passes --
    ``baseline_mean_offset`` (the training offsets' mean) and ``baseline_window_mean`` (each
    window's mean IMU sample minus the training set's, no learning) -- ``offsets (K, C)`` and
    ``windows``."""
    s0 = first_seed(state, seeds)
    config = s0.config
    n = int(sum(len(p.indices) for p in parts))
    if offsets is None:
        offsets = validation_draws(state, seeds, draws)
    offsets = np.atleast_2d(np.asarray(offsets, np.float32))
    bs = config.train.batch_size
    loss = np.zeros(seeds)
    sums: dict[str, np.ndarray] | None = None
    step = eval_step_seeds if seeds > 1 else eval_step
    clean_means, biases = [], []
    for b in progress_bar(range(0, n, bs), desc="validation", enabled=show, unit="batch"):
        flat = np.arange(b, min(b + bs, n))
        batch = gather(parts, flat, config.model, config.injection.single_sensor, bs,
                       label=config.injection.target)
        clean_means.append(_window_means(batch)[:flat.size])
        if "bias" in batch:
            biases.append(batch["bias"][:flat.size])
        for o in offsets:
            batch["offset"] = np.broadcast_to(o, (bs, o.size)).copy()
            m = jax.device_get(step(state, batch))
            loss += np.reshape(m["loss"], -1) * flat.size
            sums = m["sums"] if sums is None else jax.tree.map(np.add, sums, m["sums"])
    per_seed = []
    for k in range(seeds):
        sk = jax.tree.map(lambda x, k=k: x[k], sums) if seeds > 1 else sums
        per_seed.append(jax.tree.map(lambda x: np.asarray(x).tolist(), metrics_from_sums(sk)))
    true = np.repeat(offsets, n, axis=0)  # (K * n, C), pass by pass
    mean_pred = np.asarray(mean_offset_baseline(state, seeds))
    window_pred = (np.concatenate(clean_means)[None] + offsets[:, None]
                   - np.asarray(s0.imu_stats.mean)).reshape(true.shape)
    if biases:  # the total label: the sensor's own bias is part of the truth
        true = true + np.tile(np.concatenate(biases), (len(offsets), 1))
        known = np.zeros_like(mean_pred) if label_bias is None else np.asarray(label_bias)
        mean_pred, window_pred = mean_pred + known, window_pred + known
    mean_pred = np.broadcast_to(mean_pred, true.shape)
    baselines = {f"baseline_{name}": jax.tree.map(
        lambda x: np.asarray(x).tolist(),
        calibration_metrics(jnp.asarray(pred, jnp.float32), jnp.asarray(true)))
        for name, pred in (("mean_offset", mean_pred), ("window_mean", window_pred))}
    loss = (loss / max(n * len(offsets), 1)).tolist()
    return {"loss": loss[0] if seeds == 1 else loss, "metrics": per_seed, **baselines,
            "offsets": offsets.tolist(), "windows": n}


def read_run_config(run_dir: str | Path) -> CalibRunConfig:
    """The :class:`~uavcal_jax.calib.config.CalibRunConfig` of a run folder's ``config.json``
    (either layout: :func:`~uavcal_jax.calib.config.run_layout`).

    Raises:
        DataError: no or an unreadable ``config.json``, or settings the root does not have.
    """
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise DataError(f"not a calib run folder (no {CONFIG_FILE})", run_dir)
    try:
        stored = json.loads(path.read_text())
        settings = {k: v for k, v in run_layout(stored).items() if k not in RUN_EXTRAS}
        return from_dict(CalibRunConfig, settings)
    except (ValueError, AttributeError) as err:  # ConfigError and JSONDecodeError included
        raise DataError(f"{CONFIG_FILE} does not describe a calib run ({err})",
                        path) from None


def _abstract_tree(config: CalibConfig, parts: list[Windows], stats: ImuStats,
                   seeds: int) -> dict:
    """The structure of a checkpoint's state item: the state and the run's key data."""
    return {"state": _init_state(config, parts, stats, seeds, abstract=True),
            "key": jax.ShapeDtypeStruct((2,), jnp.uint32)}


def _spec(run: CalibRunConfig, windows: list[Windows],
          inputs: Mapping[str, Any] | None = None, ignore: frozenset[str] = RESUMABLE_KEYS
          ) -> RunSpec:
    """The run folder's record of ``run`` trained on ``windows`` (``config.json`` and what
    a checkpoint must match but for ``ignore``)."""
    return RunSpec(config=run, resolved=resolved_config(run, windows),
                   extras={**_window_shape(windows),
                           **({} if inputs is None else {"command": dict(inputs)})},
                   ignore=ignore, defaults=to_dict(CalibRunConfig()), layout=run_layout,
                   keep=run.loop.keep, meta={"seeds": run.train.seeds})


def _restore(run_dir: str | Path, parts: list[Windows], kind: str,
             run: CalibRunConfig | None = None) -> tuple[dict, dict, int]:
    """``(tree, meta, seeds)`` of a run folder's ``kind`` checkpoint, restored under ``run``
    (default the run's own configuration)."""
    run = read_run_config(run_dir) if run is None else run
    config, seeds = run.calib, run.train.seeds
    stats = training_statistics(parts, config.model.imu_channels,
                                config.injection.single_sensor)
    spec = _spec(run, parts, ignore=INFERENCE_KEYS)
    with Checkpoints(run_dir, read_only=True) as ckpt:
        tree, meta = ckpt.restore(kind, _abstract_tree(config, parts, stats, seeds),
                                  spec.resolved, ignore=spec.ignore, defaults=spec.defaults,
                                  layout=spec.layout)
    return tree, meta, seeds


def restore_run(run_dir: str | Path, parts: list[Windows], kind: str = "best",
                run: CalibRunConfig | None = None) -> tuple[CalibState, int]:
    """``(state, seeds)`` of a run folder's ``kind`` checkpoint (``"best"`` or ``"last"``);
    ``parts`` (windows cut with the run's window configuration) fix the input shapes and
    must match the run's (one-line :class:`DataError` otherwise). ``run``: the configuration
    to restore under (the run's own, :func:`read_run_config`, with a command's ``--set``);
    it must match the checkpoint's but for :data:`INFERENCE_KEYS` (one-line
    :class:`DataError` naming the differences otherwise), and the state carries it."""
    tree, _, seeds = _restore(run_dir, parts, kind, run)
    return tree["state"], seeds


def export_weights(run_dir: str | Path, target: str | Path, parts: list[Windows],
                   kind: str = "best", *, closed_form_only: bool = False) -> Path:
    """Write ``target``: a run folder holding ``run_dir``'s ``config.json`` and its ``kind``
    checkpoint only, with the optimiser's moments zeroed (they compress to nothing; a
    model to predict with needs only parameters, batch statistics and the IMU statistics).
    It restores like any run (:func:`restore_run`, ``kind``) but does not resume training.
    ``closed_form_only``: the offset head's weights zeroed too
    (:func:`~uavcal_jax.calib.model.without_correction`): the model's closed form alone, the
    learned part switched off (its uncertainty head kept). Written into a temporary sibling
    and renamed, so ``target`` is whole or absent."""
    run_dir = Path(run_dir)
    tree, meta, _ = _restore(run_dir, parts, kind)
    state = tree["state"]
    if closed_form_only:
        state = state.replace(params=without_correction(state.params))
    tree["state"] = state.replace(opt_state=jax.tree.map(jnp.zeros_like, state.opt_state))

    def fill(folder: Path) -> None:
        shutil.copy2(run_dir / CONFIG_FILE, folder / CONFIG_FILE)
        with Checkpoints(folder, kinds=(kind,)) as out:
            out.save(kind, int(meta["epoch"]), tree, {**meta, "exported_from": str(run_dir)})

    return write_folder(target, fill)


def _summary_row(row: dict) -> dict:
    return {k: v for k, v in row.items() if not isinstance(v, list | dict)}


def fit(config: CalibConfig, train_windows, val_windows, run_dir: str | Path, *,
        seeds: int | None = None, resume: bool = False, progress: bool = True,
        loop: LoopConfig | None = None, stop_after: int | None = None,
        inputs: Mapping[str, Any] | None = None) -> FitResult:
    """Train ``config`` on ``train_windows``, validate on ``val_windows`` each epoch.

    Args:
        train_windows, val_windows: a WindowSet, :class:`~uavcal_jax.calib.data.Windows`, or
            a list of them (``val_windows`` may be ``None`` when ``loop.monitor`` is
            ``"train"``); all with the same frames per window and frame size.
        run_dir: the run folder (see the module docstring).
        seeds: ``K`` models in one vmapped run (default ``config.train.seeds``).
        resume: continue from the last checkpoint (same configuration; ``train.epochs`` may
            differ); the result equals that of an uninterrupted run.
        progress: tqdm bars on stderr.
        loop: run control (default :class:`~uavcal_jax.calib.config.LoopConfig`'s).
        stop_after: stop after this many epochs of this call, as if killed after that
            epoch's checkpoint (tests, smoke runs).
        inputs: the caller's other inputs (data folders, preset, command line), recorded
            in ``config.json`` under ``"command"``.

    Raises:
        DataError: no training windows, a run folder that already holds checkpoints without
            ``resume``, or a checkpoint written with another configuration or version.
    """
    seeds = config.train.seeds if seeds is None else int(seeds)
    loop = LoopConfig() if loop is None else loop
    config = apply_overrides(config, {"train.seeds": seeds})
    train, val = as_windows(train_windows), as_windows(val_windows)
    run_dir = Path(run_dir)
    n = int(sum(len(p.indices) for p in train))
    if n == 0:
        raise DataError("no training windows", run_dir)
    if loop.monitor == "val" and not val:
        raise DataError("loop.monitor=val needs validation windows", run_dir)
    run = CalibRunConfig.of(config, loop, train[0].windows.config)
    channels, sensor = config.model.imu_channels, config.injection.single_sensor
    stats = training_statistics(train, channels, sensor)
    label_bias = (mean_sensor_bias(train, channels, sensor)
                  if config.injection.target == "total" else None)
    root = _root(config)
    key_data = jax.random.key_data(root)
    bs = config.train.batch_size
    steps = -(-n // bs)
    step_fn = train_step_seeds if seeds > 1 else train_step

    def batches(epoch: int):
        order = epoch_order(root, epoch, n)
        for b in range(steps):
            flat = order[b * bs:(b + 1) * bs]
            batch = gather(train, flat, config.model, sensor, bs, label=config.injection.target)
            yield (batch, _step_keys(root, seeds, epoch * steps + b)), flat.size

    def step(state: CalibState, batch_key):
        state, m = step_fn(state, *batch_key)
        return state, {k: m[k] for k in ("loss", "tilt_deg") if k in m}

    def row(_state, means: dict) -> dict:
        loss = np.reshape(means["loss"], -1)
        out = {"loss": float(loss.mean()), "loss_per_seed": loss.tolist()}
        if config.model.tilt_head:  # the tilt head's mean angle error
            out["tilt_deg"] = float(np.mean(means["tilt_deg"]))
        return out

    def validate(state: CalibState, _epoch: int) -> dict:
        v = evaluate(state, val, seeds, draws=loop.val_offsets, label_bias=label_bias)
        vloss = np.reshape(v["loss"], -1)
        out = dict(val_loss=float(vloss.mean()), val_loss_per_seed=vloss.tolist(),
                   val_offset_rmse=float(np.mean([m["offset_rmse"] for m in v["metrics"]])),
                   val_sign_f1=float(np.mean([m["sign_f1"] for m in v["metrics"]])),
                   val_metrics=v["metrics"],
                   baseline_offset_rmse=v["baseline_mean_offset"]["offset_rmse"],
                   window_mean_offset_rmse=v["baseline_window_mean"]["offset_rmse"])
        if "z_rms" in v["metrics"][0]:  # a model with an uncertainty: its calibration
            out["val_z_rms"] = float(np.mean([m["z_rms"] for m in v["metrics"]]))
        return out

    monitored = "val_loss" if loop.monitor == "val" else "loss"
    spec = _spec(run, train, inputs)
    result = train_epochs(
        run_dir, spec, Loop(
            epochs=config.train.epochs, steps=steps, batches=batches, step=step, row=row,
            evaluate=validate if val else None,
            selection=Selection(lambda r: r[monitored], patience=config.train.patience),
            last=lambda state: {"state": state, "key": key_data},
            best=lambda state: {"state": state, "key": key_data},
            restore=lambda tree: tree["state"]),
        init=lambda: _init_state(config, train, stats, seeds),
        abstract=lambda: _abstract_tree(config, train, stats, seeds),
        resume=resume, stop_after=stop_after, progress=progress)
    state, rows = result.state, result.history
    best = next((r for r in rows if r["epoch"] == result.best.epoch), {})
    summary = {"run": str(run_dir), "seeds": seeds, "epochs": len(rows),
               "steps": int(np.reshape(jax.device_get(state.step), -1)[0]),
               "stopped_early": result.stopped, "best_epoch": result.best.epoch,
               "monitor": loop.monitor, "num_train": n,
               "num_val": int(sum(len(p.indices) for p in val)),
               "best": _summary_row(best), "final": _summary_row(rows[-1]) if rows else {}}
    return FitResult(state=state, summary=summary)
