"""Named starting points of a calibrator run, and how a run's configuration is resolved.

- :data:`PRESETS`: typed :class:`~uavcal_jax.calib.config.CalibRunConfig` instances
  (``uavcal calib train --preset``): ``paper`` (Table 2, the package defaults), ``small`` (a
  model and windows that train in minutes on a CPU) and ``shipped`` (exactly the settings of
  the weights shipped in the package, :mod:`uavcal_jax.calib.pretrained`, which
  ``experiments/calib_default_weights.py`` trains).
- :func:`resolve_configs`: a preset (or a trained run's configuration), then a command's
  arguments, then ``--set`` strings.
- :func:`budget_stride`: the experiments' budget mode's window stride.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

from uavcal_jax.calib.config import (
    CalibRunConfig,
    LossConfig,
    ModelConfig,
    TrainConfig,
)
from uavcal_jax.config import ConfigError, apply_overrides
from uavcal_jax.data.windows import WindowConfig

__all__ = ["PRESETS", "budget_stride", "resolve_configs"]

#: Table 2 of the paper: the package defaults (days per injection protocol on a 2-core CPU).
PAPER = CalibRunConfig()
#: Minutes on a CPU: 160x96 frames in 32x32 patches, 10 Hz (every 2nd frame), d 64 with 4
#: heads; pre-norm layers and AdamW at 1e-3 (post-norm layers stay at the mean offset at that
#: rate, and 1e-5 moves too little in a few hundred steps), every channel weighed in its
#: offset's units, patience 10 (one epoch's training loss carries the undifferentiable sign
#: term and fresh offsets: it is noisy). Measured in experiments/calib_ablation.py.
SMALL = CalibRunConfig(
    model=ModelConfig(d_model=64, heads=4, patch=(32, 32), norm_first=True),
    loss=LossConfig(units="standardized"),
    train=TrainConfig(learning_rate=1e-3, patience=10),
    window=WindowConfig(size=(160, 96), frame_step=2))
#: The shipped weights' training: ``small`` with the physical protocol (offsets in the range of
#: real IMU biases, like the demo's) and its ``total`` label (what a user subtracts), the
#: motion tokens of the front end's visual rotations, the head starting at the metric closed
#: form (``rotation_alignment``: the gyro's least squares against the camera's rotations, the
#: accelerometer's visual-inertial alignment of the stereo VIO's poses over the 20 s around
#: each window; issue 43) with a correction in units of 0.05 offset standard deviations, an
#: uncertainty head (``model.variance``), 2 s windows every 0.5 s at the full 20 Hz, at most
#: 60 epochs with patience 6 on the validation loss, the best checkpoint only. The weights
#: shipped are this run with its learned correction switched off
#: (:func:`~uavcal_jax.calib.loop.export_weights` ``closed_form_only``): on unseen flights
#: it made the estimate worse (:mod:`uavcal_jax.calib.pretrained`).
SHIPPED = apply_overrides(SMALL, {
    "injection.protocol": "physical", "train.epochs": 60, "train.patience": 6,
    "model.motion_tokens": True, "model.closed_form": "rotation_alignment",
    "model.correction_scale": 0.05, "model.variance": True, "window.rotations": "visual",
    "window.accel_start": "alignment", "window.alignment_span": 20.0,
    "window.duration": 2.0, "window.stride": 0.5, "window.frame_step": 1,
    "loop.monitor": "val", "loop.keep": 1})
#: The named presets (``--preset``).
PRESETS: dict[str, CalibRunConfig] = {"paper": PAPER, "small": SMALL, "shipped": SHIPPED}


def resolve_configs(sets: Sequence[str] | Mapping[str, Any] = (), *,
                    preset: str | CalibRunConfig = "paper", protocol: str | None = None,
                    validation: str | None = None, seeds: int | None = None,
                    epochs: int | None = None,
                    arguments: Mapping[str, Any] | None = None) -> CalibRunConfig:
    """A run's configuration: ``preset`` (a name of :data:`PRESETS` or an instance, e.g. a
    trained run's :func:`~uavcal_jax.calib.loop.read_run_config`), then the arguments
    (``protocol``: ``injection.protocol``, ``validation``: ``loop.validation``, ``seeds``,
    ``epochs``: ``train.*``, and ``arguments``, typed values keyed like ``sets``; ``None``
    keeps the preset's value), then ``sets`` (``"key=value"`` strings or a mapping), which
    win.

    Raises:
        UnknownConfigKey: an unknown key (a ``KeyError`` and a ``DataError``; the message
            names it and lists the valid ones).
        ConfigError: an unknown preset, a setting that is not ``key=value``, does not parse,
            or fails validation (a ``ValueError`` and a ``DataError``).
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ConfigError(f"unknown preset {preset!r}; presets: {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    given = {"injection.protocol": protocol, "loop.validation": validation,
             "train.seeds": seeds, "train.epochs": epochs, **(arguments or {})}
    return apply_overrides(apply_overrides(preset, {k: v for k, v in given.items()
                                                    if v is not None}), sets)


def _keys(sets: Sequence[str] | Mapping[str, Any]) -> set[str]:
    return {s.split("=", 1)[0].strip() for s in sets} if not isinstance(sets, Mapping) \
        else set(sets)


def budget_stride(run: CalibRunConfig, mode: CalibRunConfig,
                  sets: Sequence[str] | Mapping[str, Any] = ()) -> CalibRunConfig:
    """The experiments' budget mode (``calib_protocols.py``, ``calib_ablation.py`` without
    ``--paper``): ``run`` with a window every ``mode.window.duration`` seconds, unless
    ``sets`` (the settings that made ``run``) give ``window.stride``.

    ``mode`` is the mode's own configuration (its preset and the user's ``--set``): with
    ``small``'s 10 s windows, non-overlapping windows, the same data per epoch at a tenth of
    the paper's 1 s stride's cost. A script's settings that change the window length (an
    ablation over ``window.duration``) keep that stride, as the paper keeps its 1 s, so every
    window length has as many windows, and as many steps per epoch.
    """
    if "window.stride" in _keys(sets):
        return run
    return dataclasses.replace(
        run, window=dataclasses.replace(run.window, stride=mode.window.duration))
