"""The calibrator's validation trials and their run folders, for ``uavcal calib`` and the
experiments (``calib_protocols.py``, ``calib_ablation.py``).

- :func:`validation_trials`: the trials of ``loop.validation`` (section 4.3 of the paper): the
  fixed random split over windows, leave-one-sequence-out, or k-fold over contiguous blocks of
  windows; :func:`spread` picks some of them evenly.
- Run folders: a one-trial run is its own folder; a loo/kfold run holds one folder per trial,
  ``RUN/trial_NN`` (:data:`TRIAL_FORMAT`, :func:`trial_dir`, :func:`trial_dirs`). Each holds
  ``data.json`` (:func:`write_trial_data`, :func:`trial_sides`): the windows of each side as
  ``{"train"|"val": [{"source": folder, "indices": [...]}, ...]}``, from which
  :func:`validation_windows` rebuilds the validation side.
- :func:`run_trials`: fit every trial of a scheme into its folder.
- :func:`mean_std`, :func:`mean_std_of`: the mean and standard deviation over trials (Table 4).
- :func:`least_squares_trial`: the least-squares baseline on a trial's validation windows.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import jax
import numpy as np

from uavcal_jax.calib.baselines import (
    LeastSquaresConfig,
    ground_truth_bias_windows,
    least_squares_windows,
)
from uavcal_jax.calib.config import CalibConfig, LoopConfig
from uavcal_jax.calib.data import (
    Windows,
    kfold_windows,
    leave_one_out,
    load_windows,
    split_windows,
)
from uavcal_jax.calib.loop import fit
from uavcal_jax.calib.metrics import calibration_metrics
from uavcal_jax.calib.predict import expand_to_six
from uavcal_jax.data.windows import WindowConfig
from uavcal_jax.errors import DataError

__all__ = ["DATA_FILE", "LS_CONFIGS", "TRIAL_FORMAT", "Trial", "bootstrap_interval",
           "least_squares_trial", "mean_std",
           "mean_std_of", "run_trials", "spread", "trial_dir", "trial_dirs", "trial_folders",
           "trial_sides", "validation_trials", "validation_windows", "write_trial_data"]

#: ``(train, val)`` windows of one trial.
Trial = tuple[list[Windows], list[Windows]]
#: Trial folder names of loo/kfold runs (``trial_00``, ...), by the trial's index among all
#: the scheme's trials.
TRIAL_FORMAT = "trial_{:02d}"
_TRIAL_GLOB = "trial_*"
#: A run folder's record of its windows.
DATA_FILE = "data.json"


def validation_trials(parts: list[Windows], loop: LoopConfig) -> list[Trial]:
    """``[(train, val), ...]`` of ``loop.validation``: one split, one trial per sequence
    (loo) or ``loop.folds`` contiguous blocks of windows (kfold)."""
    if loop.validation == "split":
        return split_windows(parts, loop.val_fraction, loop.split_seed)
    if loop.validation == "loo":
        return leave_one_out(parts)
    return kfold_windows(parts, loop.folds)


def spread(n: int, k: int | None) -> list[int]:
    """``k`` of the indices ``0..n-1`` spread evenly, first and last included (``None`` or
    ``k >= n``: all)."""
    if k is None or k >= n:
        return list(range(n))
    return sorted({int(i) for i in np.linspace(0, n - 1, k).round()})


# ----------------------------------------------------------------------------- run folders


def trial_dir(out: str | Path, index: int, trials: int) -> Path:
    """The folder of trial ``index`` of ``trials`` in the run ``out``: ``out`` itself for a
    one-trial run, else ``out/trial_NN``."""
    out = Path(out)
    return out if trials == 1 else out / TRIAL_FORMAT.format(index)


def trial_folders(run: str | Path) -> list[Path]:
    """The trial folders of a loo/kfold run (those holding a ``config.json``), sorted; empty
    for a one-trial run or another folder."""
    return sorted(p for p in Path(run).glob(_TRIAL_GLOB) if (p / "config.json").is_file())


def trial_dirs(run: str | Path) -> list[Path]:
    """The fit folders of ``run``: itself, or its trial folders.

    Raises:
        DataError: neither a ``config.json`` nor trial folders.
    """
    run = Path(run)
    if (run / "config.json").is_file():
        return [run]
    trials = trial_folders(run)
    if not trials:
        raise DataError(f"not a calib run folder (no config.json, no {_TRIAL_GLOB}/)", run)
    return trials


def trial_sides(train: Iterable[Windows], val: Iterable[Windows]) -> dict:
    """A run folder's ``data.json``: the windows of each side (``calib eval`` reads the
    validation side)."""
    return {side: [{"source": p.source, "indices": p.indices.tolist()} for p in ps]
            for side, ps in (("train", train), ("val", val))}


def write_trial_data(run_dir: str | Path, train: Iterable[Windows], val: Iterable[Windows]
                     ) -> Path:
    """Create ``run_dir`` and write its ``data.json`` (:func:`trial_sides`); returns
    ``run_dir``."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / DATA_FILE).write_text(json.dumps(trial_sides(train, val)) + "\n")
    return run_dir


def validation_windows(run_dir: str | Path, window: WindowConfig,
                       cache: dict[str, Windows] | None = None) -> list[Windows]:
    """The validation side of a run folder's ``data.json``, its sequences cut by ``window``
    (the run's); ``cache`` (source -> every window of it) lets trials share a sequence's
    load.

    Raises:
        DataError: no ``data.json`` in ``run_dir``.
    """
    run_dir = Path(run_dir)
    path = run_dir / DATA_FILE
    if not path.is_file():
        raise DataError(f"no {DATA_FILE}: give --data", run_dir)
    cache = {} if cache is None else cache
    parts = []
    for entry in json.loads(path.read_text())["val"]:
        if entry["source"] not in cache:
            (cache[entry["source"]],) = load_windows([entry["source"]], window)
        w = cache[entry["source"]]
        parts.append(Windows(w.windows, np.asarray(entry["indices"], np.int64), w.source))
    return parts


# ----------------------------------------------------------------------------- running


def run_trials(config: CalibConfig, loop: LoopConfig, trials: Sequence[Trial],
               out: str | Path, *, resume: bool = False, progress: bool = True,
               stop_after: int | None = None, inputs: Mapping | None = None) -> list[dict]:
    """Fit ``config`` on every trial into its folder (:func:`trial_dir`, with its
    ``data.json``) by :func:`uavcal_jax.calib.loop.fit` (``inputs``: the caller's other
    inputs, recorded in each ``config.json``); returns each fit's summary with
    ``held_out``, the sources of its validation side."""
    results = []
    for i, (train, val) in enumerate(trials):
        run_dir = write_trial_data(trial_dir(out, i, len(trials)), train, val)
        res = fit(config, train, val, run_dir, resume=resume, progress=progress, loop=loop,
                  stop_after=stop_after, inputs=inputs)
        results.append({**res.summary, "held_out": [p.source for p in val]})
    return results


# ----------------------------------------------------------------------------- statistics


def mean_std(values: Iterable[float | None]) -> dict | None:
    """``{"mean", "std", "values"}`` of the finite ``values`` (population standard
    deviation); ``None`` when there is none."""
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return None
    return {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "values": vals}


def mean_std_of(rows: Sequence[Mapping], keys: Iterable[str]) -> dict[str, dict | None]:
    """:func:`mean_std` over ``rows`` (one per trial) of each of ``keys`` (a missing key
    counts as no value)."""
    return {k: mean_std([r.get(k) for r in rows]) for k in keys}


def bootstrap_interval(values: Iterable[float | None], *, level: float = 0.95,
                       resamples: int = 10_000, seed: int = 0) -> dict | None:
    """The mean of the finite ``values`` (one per trial: a paired difference, a metric) with
    its percentile bootstrap interval over trials (Efron and Tibshirani 1993, ch. 13):
    ``{"mean", "low", "high", "n", "level"}``; ``None`` without a value. With one value the
    interval is that value (no spread to resample)."""
    vals = np.array([float(v) for v in values if v is not None and np.isfinite(v)])
    if vals.size == 0:
        return None
    rng = np.random.default_rng(seed)
    means = vals[rng.integers(0, vals.size, size=(resamples, vals.size))].mean(axis=1)
    tail = 100.0 * (1.0 - level) / 2.0
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return {"mean": float(vals.mean()), "low": float(low), "high": float(high),
            "n": int(vals.size), "level": level}


#: Least squares on the injected streams: the paper protocol's gyro offsets reach ~1 rad/s,
#: past the real bias sizes for which 3 Gauss-Newton iterations converge; 0.1 s keyframes
#: are the fallback when a 0.25 s interval rotates past the preintegration's range.
#: One window per solve (``chunk=1``): every trial's windows then share one compiled solve,
#: where a chunk of ``min(32, windows)`` compiles anew for each held-out window count.
LS_CONFIGS = (LeastSquaresConfig(iterations=6, chunk=1),
              LeastSquaresConfig(interval=0.1, iterations=6, chunk=1))


def _plain(tree):
    return jax.tree.map(lambda x: np.asarray(x).tolist(), tree)


def least_squares_trial(val, offsets: np.ndarray, sensor: str, ground_truth) -> dict:
    """Least squares on every validation window once per offset of ``offsets (K, C)``
    (injected into every window): metrics pooled over the K passes, raw and minus the true
    bias, and the per-window estimates of the first offset (Figure 2); ``ground_truth(source)``
    reads a sequence's."""
    pick = (slice(None) if offsets.shape[1] == 6 else
            slice(0, 3) if sensor == "gyro" else slice(3, 6))
    subs = [(p.windows.subset(p.indices), ground_truth(p.source)) for p in val]
    bias = np.concatenate([ground_truth_bias_windows(sub, gt) for sub, gt in subs])[:, pick]
    last_err = None
    for cfg in LS_CONFIGS:
        try:
            raw = np.stack([np.concatenate([
                np.asarray(least_squares_windows(
                    sub, gt, np.broadcast_to(expand_to_six(o, sensor), (len(sub), 6)), cfg),
                    np.float64) for sub, gt in subs])[:, pick] for o in offsets])
            break
        except DataError as err:
            last_err = err
    else:
        return {"error": str(last_err)}
    oracle = raw - bias  # (K, n, C)
    target = np.broadcast_to(offsets[:, None], raw.shape).reshape(-1, raw.shape[-1])
    return {"interval_s": cfg.interval, "per_window": raw[0], "oracle_per_window": oracle[0],
            "metrics": _plain(calibration_metrics(raw.reshape(target.shape), target)),
            "oracle_metrics": _plain(calibration_metrics(oracle.reshape(target.shape),
                                                         target))}
