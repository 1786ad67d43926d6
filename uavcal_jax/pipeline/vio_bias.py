"""``vio-bias``: the IMU offset as the stereo VIO's own bias estimate.

The VIO (:func:`uavcal_jax.vio.run.run_vio`) carries a gyro and an accelerometer bias in
every frame's state and solves for them with the poses; a constant offset in the IMU is,
to the VIO, part of that bias. The gyro estimate is the per-axis median of the bias states of
the frames the VIO tracked (status ``tracking``: solved with landmarks, no failure reset, no
coasting) over the last :attr:`VioBiasOptions.tail_fraction` of the flight: the first part
is left out because the biases start at zero and take a few seconds of motion to converge.

The accelerometer's is, by default (``accel="alignment"``), a batch alignment of the VIO's
trajectory with the IMU over the whole flight
(:func:`uavcal_jax.imu.accel_alignment.align_accel_bias`): the window's bias states trade the
bias across gravity against the tilt and stay there for many seconds (``accel="states"``
takes their median as for the gyro). Its label is ``total``: the VIO sees the whole constant
error, offset and the sensor's own bias alike. :func:`estimate` runs its own VIO;
:func:`from_vio` reads the estimate from a VIO run already made on the recorded IMU (``uavcal
run``'s one pass).

Measured (``uavcal demo``: 12 s procedural flight, seed 9, 121 degrees of yaw), errors against
the total: gyro 2e-4, -1e-4, -4e-4 rad/s; accelerometer (gravity along x) -0.006, -0.020,
-0.009 m/s^2 aligned, against 0.043, 0.114, 0.125 from the states, with a truth of -0.163,
-0.137, -0.099. ``uavcal simulate --trajectory V2_01_easy.txt --start 5 --duration 40 --seed 4
--imu-offset 0.03,-0.045,0.02,0.12,-0.08,0.1``, then ``uavcal calib predict``, states: -1.0e-4,
0.5e-4, -0.9e-4 rad/s and 1.1e-3, 9.9e-3, -0.4e-3 m/s^2 (534 of 801 frames, no reset);
``transformer`` with the shipped weights 0.025, 0.026, -0.004 rad/s and -0.110, -0.080,
-0.034 m/s^2.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from uavcal_jax.config import apply_overrides
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.imu.accel_alignment import align_accel_bias
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.pipeline.offset_estimate import (
    SIX_CHANNELS,
    OffsetEstimate,
    OffsetMethod,
    check_sequence,
)
from uavcal_jax.pipeline.offset_uncertainty import recording_sigma
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.run import VioResult, run_vio

__all__ = ["ACCEL_SOURCES", "GOOD_STATUSES", "METHOD", "TAIL_FRACTION", "VioBiasOptions",
           "configure", "estimate", "from_vio", "tail_median"]

#: Frame statuses (:class:`uavcal_jax.vio.frame_estimate.FrameEstimate`) whose bias state
#: counts: solved with landmarks. Not ``initialized`` (the biases are still their prior),
#: ``coasting`` (IMU propagation: nothing observes the biases), ``reset`` (a failure check
#: fired).
GOOD_STATUSES = ("tracking",)
#: The share of a flight, at its end, that the VIO-based offset estimators (this one and
#: :mod:`uavcal_jax.pipeline.self_calib`) read: the VIO's biases take a few seconds to settle.
TAIL_FRACTION = 2.0 / 3.0
#: Where the accelerometer estimate comes from (:attr:`VioBiasOptions.accel`).
ACCEL_SOURCES = ("alignment", "states")
#: Seconds per batch-means block of the bias states
#: (:func:`~uavcal_jax.pipeline.offset_uncertainty.recording_sigma`): a VIO's window forgets
#: its bias states' noise over a few seconds.
STATE_BLOCK_S = 3.0
#: The sigma's calibration per channel (gyro xyz, then accel xyz from the states), measured by
#: ``experiments/calib_uncertainty.py`` on flights apart from those the tables judge it on:
#: the 11 EuRoC trajectories from 40 s in, 20 s each, seed 11 (gyro: the states' batch
#: means gave z-scores of RMS 7.2, the states' errors persisting past any block a 13 s tail
#: holds). The accelerometer's default sigma is the alignment's own (z RMS 1.08 there); the
#: states' accelerometer scale is not measured.
SIGMA_SCALE = (7.2, 7.2, 7.2, 1.0, 1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class VioBiasOptions:
    """The ``vio-bias`` method's options (``--set`` keys: ``tail_fraction``, ``vio.*``).

    Attributes:
        tail_fraction: the share of the flight, at its end, whose frames count (time from
            the first to the last camera frame); in ``(0, 1]`` (:data:`TAIL_FRACTION`).
        accel: ``"alignment"`` (the batch alignment of the tracked trajectory, module
            docstring) or ``"states"`` (the bias states' tail median, as the gyro's).
        node_spacing_s: the alignment's seconds between nodes.
        vio: the VIO's settings (:class:`~uavcal_jax.vio.config.VioConfig`; its
            camera-dependent values are resolved against the recording's left camera).
    """

    tail_fraction: float = TAIL_FRACTION
    accel: str = "alignment"
    node_spacing_s: float = 0.5
    vio: VioConfig = VioConfig()

    def __post_init__(self) -> None:
        if not 0.0 < self.tail_fraction <= 1.0:
            raise ValueError(f"tail_fraction must be in (0, 1], got {self.tail_fraction}")
        if self.accel not in ACCEL_SOURCES:
            raise ValueError(f"accel must be one of {ACCEL_SOURCES}, got {self.accel!r}")
        if not self.node_spacing_s > 0.0:
            raise ValueError(f"node_spacing_s must be > 0, got {self.node_spacing_s}")


def tail_median(t_ns: np.ndarray, values: np.ndarray, good: np.ndarray,
                tail_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """``(used, median)``: the items that are ``good`` and lie in the last ``tail_fraction``
    of the span of ``t_ns``, and the per-column median of their ``values``.

    Args:
        t_ns: ``(N,)`` int ns, increasing: every item's time (the span is its first to last).
        values: ``(N, C)`` per-item values (non-finite rows are not used).
        good: ``(N,)`` bool, the items that may count.
        tail_fraction: in ``(0, 1]``.

    Returns:
        ``used``: ``(K,)`` int indices into the items; ``median``: ``(C,)`` (NaN when ``K``
        is 0).
    """
    t_ns = np.asarray(t_ns, np.int64)
    values = np.asarray(values, np.float64)
    if t_ns.size == 0:
        return np.zeros(0, np.int64), np.full(values.shape[1:], np.nan)
    start = t_ns[-1] - tail_fraction * float(t_ns[-1] - t_ns[0])
    keep = np.asarray(good, bool) & (t_ns >= start) & np.all(np.isfinite(values), axis=1)
    used = np.flatnonzero(keep)
    if used.size == 0:
        return used, np.full(values.shape[1:], np.nan)
    return used, np.median(values[used], axis=0)


def configure(overrides: Iterable[str] = ()) -> VioBiasOptions:
    """:class:`VioBiasOptions` with ``key=value`` ``overrides`` (e.g.
    ``vio.solver.max_iterations=4``, ``tail_fraction=0.5``) applied.

    Raises:
        uavcal_jax.config.ConfigError: an unknown key (named) or a bad value.
    """
    return apply_overrides(VioBiasOptions(), list(overrides))


def estimate(sequence: Sequence, options: VioBiasOptions = VioBiasOptions(), *,
             progress: bool = False) -> OffsetEstimate:
    """The ``vio-bias`` estimate of ``sequence`` (stereo, with an IMU; no ground truth).

    ``info`` holds ``frames`` (stereo frames run), ``frames_used``, ``resets`` and
    ``tail_fraction``.

    Raises:
        DataError: what :func:`~uavcal_jax.vio.run.run_vio` refuses, or no frame tracked in
            the flight's tail.
    """
    check_sequence(sequence)
    return from_vio(sequence, run_vio(sequence, options.vio, show_progress=progress), options)


def from_vio(sequence: Sequence, result: VioResult,
             options: VioBiasOptions = VioBiasOptions()) -> OffsetEstimate:
    """The ``vio-bias`` estimate read from a VIO run already made over ``sequence``'s
    recorded IMU (no offset removed): ``uavcal run``'s own VIO pass, so that the run's
    default offset costs no second VIO. ``options.vio`` is not used (``result.config`` is
    the VIO's setting, kept in ``settings``); ``sequence`` has no ground truth.

    Raises:
        DataError: no stereo frame, or no frame tracked in the flight's tail.
    """
    check_sequence(sequence)
    frames = result.frames
    if not frames:
        raise DataError("the recording has no stereo frame for the VIO", sequence.root
                        or sequence.name)
    t_ns = np.array([f.t_ns for f in frames], np.int64)
    bias = np.stack([np.concatenate([f.bias_gyro, f.bias_accel]) for f in frames])
    good = np.isin(result.flags()["status"], GOOD_STATUSES)
    used, median = tail_median(t_ns, bias, good, options.tail_fraction)
    if used.size == 0:
        raise DataError(f"the VIO tracked no frame in the last {options.tail_fraction:.0%} of "
                        f"the flight ({len(frames)} frames, {result.resets} resets): no bias "
                        "estimate", sequence.root or sequence.name)
    info = {"frames": len(frames), "frames_used": int(used.size), "resets": result.resets,
            "tail_fraction": options.tail_fraction, "accel": options.accel}
    first_ns = int(sequence.camera("cam0").t_ns[0])
    item_t_s = (t_ns[used] - first_ns) * 1e-9
    sigma = recording_sigma(bias[used], item_t_s, STATE_BLOCK_S, scale=np.array(SIGMA_SCALE))
    if options.accel == "alignment":
        median = median.copy()
        median[3:], info["alignment"] = _aligned_accel(sequence, frames, good, median[:3],
                                                       options.node_spacing_s)
        sigma[3:] = info["alignment"]["bias_accel_std"]
    return OffsetEstimate(
        offset=median, channels=SIX_CHANNELS, median=median, per_item=bias[used],
        item_t_s=item_t_s, item="frame",
        span_ns=(int(t_ns[used[0]]), int(t_ns[used[-1]])), label="total",
        settings=dataclasses.replace(options, vio=result.config), info=info,
        sigma=np.maximum(sigma, np.finfo(np.float64).tiny))


def _aligned_accel(sequence: Sequence, frames, good: np.ndarray, bias_gyro: np.ndarray,
                   node_spacing_s: float) -> tuple[np.ndarray, dict]:
    """The accelerometer bias of :func:`~uavcal_jax.imu.accel_alignment.align_accel_bias` on
    the tracked frames' poses, and facts of the solve for ``info``."""
    tracked = [f for f, ok in zip(frames, good, strict=True) if ok and f.has_pose]
    imu = sequence.imu
    try:
        aligned = align_accel_bias(
            np.array([f.t_ns for f in tracked], np.int64),
            np.stack([f.position for f in tracked]), np.stack([f.rotation for f in tracked]),
            imu.t_ns, imu.gyro, imu.accel, bias_gyro, node_spacing_s=node_spacing_s,
            noise=(sequence.imu_calibration.noise if sequence.imu_calibration is not None
                   else EUROC_ADIS16448))
    except DataError as exc:
        raise DataError(f"vio-bias: {exc} (--set accel=states takes the VIO's bias states)",
                        sequence.root or sequence.name) from exc
    return aligned.bias_accel, {"nodes": int(aligned.nodes.size), "segments": aligned.segments,
                                "residual_rms": aligned.residual_rms,
                                "bias_accel_std": aligned.bias_std.tolist()}


METHOD = OffsetMethod(
    name="vio-bias", configure=configure, estimate=estimate,
    summary="the stereo VIO's gyro bias states, median over the tracked frames of the last "
            "tail_fraction (2/3) of the flight; the accelerometer's from a batch alignment of "
            "the VIO's trajectory with the IMU (--set tail_fraction=F, accel=alignment|states, "
            "node_spacing_s=S, vio.KEY=VALUE: the VioConfig of `uavcal vio`)")
