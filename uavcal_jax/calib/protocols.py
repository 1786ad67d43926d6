"""Validation protocols and run settings of the calibrator, shared by ``uavcal calib`` and the
experiments (``calib_protocols.py``, ``calib_ablation.py``).

- :data:`PRESETS`: named starting points, ``key=value`` settings applied before the user's:
  ``paper`` (Table 2, the package defaults) and ``small`` (a model and windows that train in
  minutes on a CPU, with the optimisation choices that make them learn; see its comment).
- :func:`resolve_configs`: ``(CalibConfig, LoopConfig, WindowConfig)`` from the preset,
  protocol, validation, seeds, epochs and ``key=value`` settings (``window.*`` and ``loop.*``
  keys go to those configurations, the rest to :class:`CalibConfig`; settings win over the
  arguments, the arguments over the preset).
- :func:`validation_trials`: the trials of a protocol (section 4.3): the fixed random split over
  windows, leave-one-sequence-out, or k-fold over contiguous blocks of windows.
- :func:`trial_sides` (a run's ``data.json``), :data:`TRIAL_FORMAT` (trial folders),
  :func:`mean_std` (the mean and standard deviation over trials of Table 4).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from uavcal_jax.calib.config import CalibConfig
from uavcal_jax.calib.data import Windows, kfold_windows, leave_one_out, split_windows
from uavcal_jax.calib.loop import LoopConfig
from uavcal_jax.config import apply_overrides
from uavcal_jax.data.windows import WindowConfig

__all__ = ["PRESETS", "SECTIONS", "TRIAL_FORMAT", "mean_std", "resolve_configs",
           "trial_sides", "validation_trials"]

#: Trial folder names of loo/kfold runs.
TRIAL_FORMAT = "trial_{:02d}"
#: Setting prefixes that are not :class:`CalibConfig` sections.
SECTIONS = ("window", "loop")
#: Named configurations (``uavcal calib train --preset``), as ``--set`` strings.
PRESETS: dict[str, tuple[str, ...]] = {
    # Table 2 of the paper: the package defaults (days per protocol on a 2-core CPU).
    "paper": (),
    # Minutes on a CPU: 160x96 frames in 32x32 patches, 10 Hz (every 2nd frame), d 64 with 4
    # heads; pre-norm layers and AdamW at 1e-3 (post-norm layers stay at the mean offset at
    # that rate, and 1e-5 moves too little in a few hundred steps), every channel weighed in
    # its offset's units, patience 10 (one epoch's training loss carries the undifferentiable
    # sign term and fresh offsets: it is noisy). Measured in experiments/calib_ablation.py.
    "small": ("model.d_model=64", "model.heads=4", "model.patch=32,32", "model.norm_first=true",
              "loss.units=standardized", "train.learning_rate=1e-3", "train.patience=10",
              "window.size=160x96", "window.frame_step=2"),
}


def _apply(config, sets: list[str], prefix: str):
    try:
        return apply_overrides(config, sets)
    except KeyError as err:
        text = str(err.args[0])
        key = text.split("'")[1] if "'" in text else text
        raise KeyError(prefix + key) from None


def resolve_configs(sets: Sequence[str], *, preset: str = "paper",
                    protocol: str | None = None, validation: str | None = None,
                    seeds: int | None = None, epochs: int | None = None
                    ) -> tuple[CalibConfig, LoopConfig, WindowConfig]:
    """The three configurations of a run: ``preset``'s settings, then the arguments (``None``
    keeps the preset's value), then ``sets``.

    Raises:
        KeyError: an unknown setting; ``args[0]`` is the full key (``"window.nope"``).
        ValueError: an unknown preset, a setting that is not ``key=value``, does not parse,
            or fails validation.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; presets: {', '.join(PRESETS)}")
    arguments = [f"{key}={value}" for key, value in (
        ("injection.protocol", protocol), ("train.seeds", seeds), ("train.epochs", epochs),
        ("loop.validation", validation)) if value is not None]
    parts: dict[str, list[str]] = {"window": [], "loop": [], "calib": []}
    for text in (*PRESETS[preset], *arguments, *sets):
        if "=" not in text:
            raise ValueError(f"{text!r} is not KEY=VALUE")
        head, _, rest = text.partition(".")
        head = head.strip()
        parts[head if head in SECTIONS else "calib"].append(rest if head in SECTIONS else text)
    return (_apply(CalibConfig(), parts["calib"], ""),
            _apply(LoopConfig(), parts["loop"], "loop."),
            _apply(WindowConfig(), parts["window"], "window."))


def validation_trials(parts: list[Windows], loop: LoopConfig
                      ) -> list[tuple[list[Windows], list[Windows]]]:
    """``[(train, val), ...]`` of ``loop.validation``: one split, one trial per sequence
    (loo) or ``loop.folds`` contiguous blocks of windows (kfold)."""
    if loop.validation == "split":
        return split_windows(parts, loop.val_fraction, loop.split_seed)
    if loop.validation == "loo":
        return leave_one_out(parts)
    return kfold_windows(parts, loop.folds)


def trial_sides(train: list[Windows], val: list[Windows]) -> dict:
    """A run folder's ``data.json``: the windows of each side (``calib eval`` reads the
    validation side)."""
    return {side: [{"source": p.source, "indices": p.indices.tolist()} for p in ps]
            for side, ps in (("train", train), ("val", val))}


def mean_std(values: Sequence[float | None]) -> dict | None:
    """``{"mean", "std", "values"}`` of the finite ``values`` (population standard
    deviation); ``None`` when there is none."""
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return None
    return {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "values": vals}
