"""``self-calib``: the IMU's constant error by differentiating through the VIO's own windows.

The stereo VIO (:func:`uavcal_jax.vio.run.run_vio`) runs once on the raw IMU; the full windows
it solves on good frames (no failure, enough landmarks) in the last
:attr:`SelfCalibOptions.tail_fraction` of the flight are kept
(:attr:`~uavcal_jax.vio.estimator.StereoVio.window_sink`): :attr:`SelfCalibOptions.windows`
of them, those nearest to times evenly spread over that span (:class:`NearestWindows`, so
only those are held in memory). In each, the bias states are pinned at zero
and the bias information taken out of the marginalisation prior
(:func:`uavcal_jax.vio.selfcalib.pin_window_biases`), so the window can only explain a
constant error in its IMU through :class:`~uavcal_jax.vio.window.CalibParams`' offset; that
offset is found from zero by preconditioned descent on the window's converged cost, its
gradient by implicit differentiation of the solve
(:func:`uavcal_jax.vio.selfcalib.descend_offset`). The estimate is the per-channel median of
the windows' offsets (label ``total``: the window sees the whole constant error).

This is the synthetic study of :mod:`uavcal_jax.vio.selfcalib` on windows the VIO built from
the recording's frames. The VIO's bias states carry the same information, window by window;
what the self-calibration adds is a gradient of the VIO's residuals with respect to the IMU's
calibration, the path through which any other calibration parameter could be learned.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import jax
import numpy as np

from uavcal_jax.config import apply_overrides
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.offset_estimate import (
    SIX_CHANNELS,
    OffsetEstimate,
    OffsetMethod,
    check_sequence,
)
from uavcal_jax.pipeline.offset_uncertainty import recording_sigma
from uavcal_jax.pipeline.vio_bias import TAIL_FRACTION
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.run import run_vio
from uavcal_jax.vio.selfcalib import DescentConfig, descend_offset, pin_window_biases

#: Seconds per batch-means block of the windows' estimates: shorter than their spacing, so
#: each window is a block of its own.
WINDOW_BLOCK_S = 0.1

__all__ = ["METHOD", "NearestWindows", "SelfCalibOptions", "configure", "estimate",
           "window_targets"]


@dataclasses.dataclass(frozen=True)
class SelfCalibOptions:
    """The ``self-calib`` method's options (``--set`` keys: ``windows``, ``tail_fraction``,
    ``sigma_gyro``, ``sigma_accel``, ``descent.*``, ``vio.*``).

    Attributes:
        windows: how many of the VIO's windows are fitted (evenly spread over the span).
        tail_fraction: the share of the flight, at its end, whose windows count (the VIO's
            biases take a few seconds to settle, and with them the points its windows'
            preintegrations are linearised at); in ``(0, 1]``.
        sigma_gyro, sigma_accel: the zero-bias pin, rad/s and m/s^2.
        descent: the descent's settings.
        vio: the VIO's settings (:class:`~uavcal_jax.vio.config.VioConfig`).
    """

    windows: int = 6
    tail_fraction: float = TAIL_FRACTION
    sigma_gyro: float = 1e-4
    sigma_accel: float = 1e-3
    descent: DescentConfig = DescentConfig(steps=4)
    vio: VioConfig = VioConfig()

    def __post_init__(self) -> None:
        if self.windows < 1:
            raise ValueError(f"windows must be >= 1, got {self.windows}")
        if not 0.0 < self.tail_fraction <= 1.0:
            raise ValueError(f"tail_fraction must be in (0, 1], got {self.tail_fraction}")
        if not (self.sigma_gyro > 0.0 and self.sigma_accel > 0.0):
            raise ValueError("sigma_gyro and sigma_accel must be > 0")


def configure(overrides: Iterable[str] = ()) -> SelfCalibOptions:
    """:class:`SelfCalibOptions` with ``key=value`` ``overrides`` (e.g. ``windows=4``,
    ``descent.steps=6``, ``vio.solver.max_iterations=4``).

    Raises:
        uavcal_jax.config.ConfigError: an unknown key (named) or a bad value.
    """
    return apply_overrides(SelfCalibOptions(), list(overrides))


def window_targets(first_ns: int, last_ns: int, count: int, tail_fraction: float
                   ) -> np.ndarray:
    """``(count,)`` int ns: times evenly spread over the last ``tail_fraction`` of
    ``[first_ns, last_ns]``, its ends included (one time, the end, for ``count`` 1)."""
    start = last_ns - tail_fraction * float(last_ns - first_ns)
    if count == 1:
        return np.array([last_ns], np.int64)
    return np.round(np.linspace(start, last_ns, count)).astype(np.int64)


class NearestWindows:
    """A :attr:`~uavcal_jax.vio.estimator.StereoVio.window_sink` keeping, for each of
    ``targets`` (int ns), the window solved nearest to it at or after ``targets[0]``: at most
    ``len(targets)`` windows are held, whatever the flight's length.

    Attributes:
        kept: per target, ``(t_ns, state, problem, params)`` or ``None``.
    """

    def __init__(self, targets: np.ndarray):
        self.targets = np.asarray(targets, np.int64)
        self.kept: list[tuple | None] = [None] * len(self.targets)
        self._gap = np.full(len(self.targets), np.inf)

    def __call__(self, t_ns: int, state, problem, params) -> None:
        if t_ns < self.targets[0]:
            return
        gaps = np.abs(self.targets - t_ns).astype(np.float64)
        i = int(np.argmin(gaps))
        if gaps[i] < self._gap[i]:
            self._gap[i] = gaps[i]
            self.kept[i] = (int(t_ns), state, problem, params)

    def windows(self) -> list[tuple]:
        """The kept windows, in time order."""
        return sorted((w for w in self.kept if w is not None), key=lambda w: w[0])


def estimate(sequence: Sequence, options: SelfCalibOptions = SelfCalibOptions(), *,  # noqa: B008
             progress: bool = False) -> OffsetEstimate:
    """The ``self-calib`` estimate of ``sequence`` (stereo, with an IMU; no ground truth).
    Per item: each window's offset.

    ``info`` holds ``frames``, ``resets``, ``windows_tried``, ``windows_used`` (those whose fit
    stayed finite), each one's ``window_sigma`` (W, 6) (the Hessian's Cramer-Rao standard
    deviation, rad/s and m/s^2). The estimate's sigma is the windows' batch-means standard
    error (each window a block: they lie seconds apart) with their median Cramer-Rao sigma
    over the root of their count as what they share
    (:func:`~uavcal_jax.pipeline.offset_uncertainty.recording_sigma`).

    Raises:
        DataError: what :func:`~uavcal_jax.vio.run.run_vio` refuses, no full window in the
            flight's tail, or none whose fit stayed finite.
    """
    check_sequence(sequence)
    t_frames = np.asarray(sequence.camera("cam0").t_ns, np.int64)
    sink = NearestWindows(window_targets(int(t_frames[0]), int(t_frames[-1]), options.windows,
                                         options.tail_fraction))
    result = run_vio(sequence, options.vio, show_progress=progress, window_sink=sink)
    windows = sink.windows()
    if not windows:
        raise DataError(f"the VIO solved no full window on a good frame in the last "
                        f"{options.tail_fraction:.0%} of the flight ({len(result.frames)} "
                        f"frames, {result.resets} resets): no self-calibration",
                        sequence.root or sequence.name)
    estimates, sigmas, fitted = [], [], []
    bar = progress_bar(total=len(windows), desc="self-calib windows", enabled=progress,
                       unit="window")
    with jax.enable_x64(True):
        for t_ns, state, problem, params in windows:
            start, pinned = pin_window_biases(state, problem, options.sigma_gyro,
                                              options.sigma_accel)
            fit = descend_offset([pinned], [params], [start], options.descent)
            if fit["finite"]:
                fitted.append(t_ns)
                estimates.append(fit["estimate"])
                sigmas.append(fit["sigma"])
            bar.update(1)
    bar.close()
    if not estimates:
        raise DataError(f"no window's fit stayed finite ({len(windows)} tried): no "
                        "self-calibration", sequence.root or sequence.name)
    per_window = np.stack(estimates)
    median = np.median(per_window, axis=0)
    t_ns = np.array(fitted, np.int64)
    info = {"frames": len(result.frames), "resets": result.resets,
            "windows_tried": len(windows), "windows_used": len(fitted),
            "tail_fraction": options.tail_fraction,
            "window_sigma": np.stack(sigmas).tolist()}
    item_t_s = (t_ns - t_frames[0]) * 1e-9
    sigma = recording_sigma(per_window, item_t_s, WINDOW_BLOCK_S, common=np.median(
        np.stack(sigmas), axis=0) / np.sqrt(len(fitted)))
    return OffsetEstimate(
        offset=median, channels=SIX_CHANNELS, median=median, per_item=per_window,
        item_t_s=item_t_s, item="window",
        span_ns=(int(t_ns[0]), int(t_ns[-1])), label="total",
        settings=dataclasses.replace(options, vio=result.config), info=info,
        sigma=np.maximum(sigma, np.finfo(np.float64).tiny))


METHOD = OffsetMethod(
    name="self-calib", configure=configure, estimate=estimate,
    summary="differentiates through the VIO's own windows: their biases pinned at zero, the "
            "offset that minimises each window's converged cost, by implicit gradients; "
            "median over windows in the last tail_fraction of the flight (--set windows=N, "
            "tail_fraction=F, descent.steps=N, vio.KEY=VALUE)")
