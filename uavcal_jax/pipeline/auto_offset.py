"""``auto``: every named estimator on the recording, fused per channel by inverse variance.

Each component method (:attr:`AutoOptions.methods`) estimates the offset with its own
standard deviation (:attr:`~uavcal_jax.pipeline.offset_estimate.OffsetEstimate.sigma`, the
items' correlation accounted for). Per channel the estimate is the inverse-variance weighted
mean of the methods that estimate that channel, ``x = sum(x_m / s_m^2) / sum(1 / s_m^2)``,
with ``s = sum(1 / s_m^2)^(-1/2)``: the vision-based gyro outweighs a learned one where the
camera's rotations are good, and a learned accelerometer outweighs the VIO's alignment where
the flight turned too little to tell the bias from the tilt (the alignment's sigma then grows
towards its prior). A method that fails (refuses the recording: too short, the VIO lost) or
gives no sigma is skipped, and says so in ``info["methods"]``. A channel no method
determined (every sigma infinite) is not corrected (0) and its sigma stays infinite.

The fusion takes the methods' errors as independent. They are not wholly: ``vio-bias`` and
``visual-ls`` read the same frames. Where they share an error the fused sigma is too small by
at most a factor ``sqrt(M)`` for ``M`` equally weighted methods; in practice one method
dominates each channel (measured: ``experiments/calib_blind.py``'s z-scores).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable

import numpy as np

from uavcal_jax.config import apply_overrides
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline import self_calib, transformer_offset, vio_bias, visual_ls
from uavcal_jax.pipeline.offset_estimate import (
    SIX_CHANNELS,
    OffsetEstimate,
    OffsetMethod,
    check_sequence,
)
from uavcal_jax.vio.visual_gyro import VisualGyroConfig

__all__ = ["COMPONENTS", "DEFAULT_COMPONENTS", "METHOD", "AutoOptions", "AutoSettings",
           "configure", "estimate", "fuse"]

#: The methods ``auto`` can fuse, by name.
COMPONENTS = {m.name: m for m in (vio_bias.METHOD, visual_ls.METHOD, self_calib.METHOD,
                                  transformer_offset.METHOD)}
#: Fused when none are named: the self-calibration is left out by default (28-90 s per 30 s
#: flight, and the VIO's bias states and alignment read the same windows).
DEFAULT_COMPONENTS = ("vio-bias", "visual-ls", "transformer")


def _check_methods(methods: tuple[str, ...]) -> None:
    bad = [m for m in methods if m not in COMPONENTS]
    if bad or not methods or len(set(methods)) != len(methods):
        raise ValueError(f"methods must be distinct names of {', '.join(COMPONENTS)}, got "
                         f"{list(methods)}")


@dataclasses.dataclass(frozen=True)
class AutoSettings:
    """What ``auto`` adds to the other methods' options in a config tree that holds theirs
    already (``uavcal run --set offset.auto.methods=...``).

    Attributes:
        methods: the component methods, names of :data:`COMPONENTS`.
    """

    methods: tuple[str, ...] = DEFAULT_COMPONENTS

    def __post_init__(self) -> None:
        _check_methods(self.methods)


@dataclasses.dataclass(frozen=True)
class AutoOptions:
    """The ``auto`` method's options (``--set methods=vio-bias,transformer``,
    ``vio_bias.tail_fraction=0.5``, ``transformer.kind=last``, ...).

    Attributes:
        methods: the component methods, names of :data:`COMPONENTS`.
        vio_bias, visual_ls, self_calib: those methods' options.
        transformer: the transformer's run folder and checkpoint
            (:class:`~uavcal_jax.pipeline.transformer_offset.TransformerSettings`; the run
            is read when the estimate runs).
    """

    methods: tuple[str, ...] = DEFAULT_COMPONENTS
    vio_bias: vio_bias.VioBiasOptions = vio_bias.VioBiasOptions()
    visual_ls: VisualGyroConfig = VisualGyroConfig()
    self_calib: self_calib.SelfCalibOptions = self_calib.SelfCalibOptions()
    transformer: transformer_offset.TransformerSettings = transformer_offset.TransformerSettings()

    def __post_init__(self) -> None:
        _check_methods(self.methods)

    def component_options(self, name: str):
        """The options method ``name``'s ``estimate`` takes."""
        settings = getattr(self, name.replace("-", "_"))
        if isinstance(settings, transformer_offset.TransformerSettings):
            return transformer_offset.configure(**dataclasses.asdict(settings))
        return settings


def configure(overrides: Iterable[str] = (), *, checkpoint=None, kind: str | None = None,
              frame_dtype: str | None = None) -> AutoOptions:
    """:class:`AutoOptions` with ``key=value`` ``overrides``; ``checkpoint``, ``kind`` and
    ``frame_dtype`` are the transformer's (``uavcal calib predict --checkpoint``).

    Raises:
        uavcal_jax.config.ConfigError: an unknown key (named) or a bad value.
    """
    options = apply_overrides(AutoOptions(), list(overrides))
    given = {k: v for k, v in dict(checkpoint=None if checkpoint is None else str(checkpoint),
                                   kind=kind, frame_dtype=frame_dtype).items() if v is not None}
    if given:
        options = dataclasses.replace(
            options, transformer=dataclasses.replace(options.transformer, **given))
    return options


def fuse(estimates: list[OffsetEstimate]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(offset (6,), sigma (6,), weights (M, 6))``: the inverse-variance fusion of
    ``estimates`` (each with a sigma) per channel; a channel none determines has offset 0,
    sigma ``inf`` and weights 0. Weights sum to 1 over the methods on a determined channel."""
    m = len(estimates)
    value = np.zeros((m, 6))
    precision = np.zeros((m, 6))
    for k, est in enumerate(estimates):
        at = est.channel_index
        value[k, at] = np.asarray(est.median, np.float64)
        sigma = np.asarray(est.sigma, np.float64)
        precision[k, at] = np.where(np.isfinite(sigma), 1.0 / np.square(sigma), 0.0)
    total = precision.sum(axis=0)
    determined = total > 0.0
    weights = np.where(determined, precision / np.where(determined, total, 1.0), 0.0)
    offset = np.where(determined, (weights * value).sum(axis=0), 0.0)
    sigma = np.where(determined, 1.0 / np.sqrt(np.where(determined, total, 1.0)), np.inf)
    return offset, sigma, weights


def estimate(sequence: Sequence, options: AutoOptions = AutoOptions(), *,  # noqa: B008
             progress: bool = False) -> OffsetEstimate:
    """The ``auto`` estimate of ``sequence`` (no ground truth). Per item: each fused method's
    estimate on the six channels (the fused value where it estimates nothing). ``info``
    holds, per component, its ``offset``, ``sigma``, ``weights`` and ``seconds``, or the
    ``error`` it failed with.

    Raises:
        DataError: every component failed or gave no sigma.
    """
    check_sequence(sequence)
    used, report = [], {}
    for name in options.methods:
        t0 = time.perf_counter()
        try:
            est = COMPONENTS[name].estimate(sequence, options.component_options(name),
                                            progress=progress)
        except DataError as exc:
            report[name] = {"error": str(exc)}
            continue
        seconds = round(time.perf_counter() - t0, 2)
        if est.sigma is None:
            report[name] = {"error": "gives no sigma (a model without model.variance)",
                            "seconds": seconds}
        elif est.label != "total":
            report[name] = {"error": f"estimates the {est.label!r} label, not the total",
                            "seconds": seconds}
        else:
            used.append(est)
            report[name] = {"channels": list(est.channels),
                            "offset": np.asarray(est.median, np.float64).tolist(),
                            "sigma": [float(v) if np.isfinite(v) else None for v in est.sigma],
                            "seconds": seconds}
    if not used:
        raise DataError("auto: no method gave an estimate with a sigma: " + "; ".join(
            f"{k}: {v['error']}" for k, v in report.items()), sequence.root or sequence.name)
    offset, sigma, weights = fuse(used)
    names = [n for n in options.methods if "error" not in report[n]]
    for name, w in zip(names, weights, strict=True):
        report[name]["weights"] = w.tolist()
    per_item = np.stack([np.where(np.isin(np.arange(6), est.channel_index),
                                  est.offset, offset) for est in used])
    determined = np.isfinite(sigma)
    starts = [est.span_ns[0] for est in used if est.span_ns[0] is not None]
    ends = [est.span_ns[1] for est in used if est.span_ns[1] is not None]
    return OffsetEstimate(
        offset=offset, channels=SIX_CHANNELS, median=offset, per_item=per_item,
        item_t_s=np.zeros(len(used)), item="method",
        span_ns=(min(starts), max(ends)) if starts else (None, None), label="total",
        settings=options, info={"methods": report, "determined": determined.tolist()},
        sigma=sigma)


METHOD = OffsetMethod(
    name="auto", configure=configure, estimate=estimate,
    arguments=("checkpoint", "kind", "frame_dtype"),
    summary="every method of --set methods=... (default vio-bias, visual-ls, transformer) "
            "fused per channel by inverse variance of their sigmas; a method that fails is "
            "skipped")
