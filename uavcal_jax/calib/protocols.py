"""Validation protocols and run settings of the calibrator, shared by ``uavcal calib`` and the
experiments (``calib_protocols.py``, ``calib_ablation.py``).

- :func:`resolve_configs`: ``(CalibConfig, LoopConfig, WindowConfig)`` from the protocol,
  validation, seeds, epochs and ``key=value`` settings (``window.*`` and ``loop.*`` keys go to
  those configurations, the rest to :class:`CalibConfig`; settings win over the arguments).
- :func:`validation_trials`: the trials of a protocol (section 4.3): the fixed random split over
  windows, leave-one-sequence-out, or k-fold over contiguous blocks of windows.
- :func:`trial_sides` (a run's ``data.json``), :data:`TRIAL_FORMAT` (trial folders),
  :func:`mean_std` (the mean and standard deviation over trials of Table 4).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from uavcal_jax.calib.config import CalibConfig, with_overrides
from uavcal_jax.calib.data import Windows, kfold_windows, leave_one_out, split_windows
from uavcal_jax.calib.loop import LoopConfig
from uavcal_jax.data.windows import WindowConfig

__all__ = ["SECTIONS", "TRIAL_FORMAT", "mean_std", "resolve_configs", "trial_sides",
           "validation_trials"]

#: Trial folder names of loo/kfold runs.
TRIAL_FORMAT = "trial_{:02d}"
#: Setting prefixes that are not :class:`CalibConfig` sections.
SECTIONS = ("window", "loop")


def _apply(config, sets: list[str], prefix: str):
    try:
        return with_overrides(config, sets)
    except KeyError as err:
        text = str(err.args[0])
        key = text.split("'")[1] if "'" in text else text
        raise KeyError(prefix + key) from None


def resolve_configs(sets: Sequence[str], *, protocol: str | None = None,
                    validation: str | None = None, seeds: int | None = None,
                    epochs: int | None = None
                    ) -> tuple[CalibConfig, LoopConfig, WindowConfig]:
    """The three configurations of a run (``None`` arguments keep the defaults).

    Raises:
        KeyError: an unknown setting; ``args[0]`` is the full key (``"window.nope"``).
        ValueError: a setting that is not ``key=value``, does not parse, or fails validation.
    """
    parts: dict[str, list[str]] = {"window": [], "loop": [], "calib": []}
    for text in sets:
        if "=" not in text:
            raise ValueError(f"{text!r} is not KEY=VALUE")
        head, _, rest = text.partition(".")
        parts[head.strip() if head.strip() in SECTIONS else "calib"].append(
            rest if head.strip() in SECTIONS else text)
    base = {k: v for k, v in (("injection.protocol", protocol), ("train.seeds", seeds),
                              ("train.epochs", epochs)) if v is not None}
    calib = _apply(with_overrides(CalibConfig(), base), parts["calib"], "")
    loop = LoopConfig() if validation is None else LoopConfig(validation=validation)
    return (calib, _apply(loop, parts["loop"], "loop."),
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
