"""What an IMU offset estimator returns (:class:`OffsetEstimate`) and how the registry holds one
(:class:`OffsetMethod`).

An estimator is a function ``estimate(sequence, options, *, progress) -> OffsetEstimate`` of a
:class:`~uavcal_jax.data.sequence.Sequence` *without ground truth* (its ``ground_truth`` is
``None``: the caller strips it, :func:`~uavcal_jax.pipeline.predict_offset.predict_offset`)
and of its own options (a frozen dataclass, or a tree of them, that its ``configure`` builds
from ``--set``-style overrides). The offset is the constant error in the recorded IMU, the
value to subtract (:func:`uavcal_jax.imu.offset.remove_offset`): gyro rad/s xyz, then accel
m/s^2 xyz, in the IMU (body) frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.data.true_offset import LABELS

__all__ = ["SIX_CHANNELS", "OffsetEstimate", "OffsetMethod", "check_sequence"]

#: The channels of a ``(6,)`` offset, in order (gyro rad/s, accel m/s^2).
SIX_CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")


@dataclass(frozen=True)
class OffsetEstimate:
    """One estimator's offset over one recording.

    Attributes:
        offset: ``(6,)`` the constant to subtract from the IMU (gyro rad/s xyz, accel m/s^2
            xyz); channels the method does not estimate are 0.
        channels: the ``C`` channels estimated (names of :data:`SIX_CHANNELS`, in its order).
        median: ``(C,)`` the estimate in those channels: the median of ``per_item`` over its
            items (``offset`` holds the same numbers in its ``channels``).
        per_item: ``(N, C)`` the estimate of each item (a window, a frame).
        item_t_s: ``(N,)`` each item's time: seconds since the first camera frame (a window's
            start, a frame's time).
        item: what an item is: ``"window"`` or ``"frame"``.
        span_ns: ``(t0, t1)`` the recording's time span the estimate covers, int ns (the
            span a ``total`` label averages the sensor's own bias over); ``(None, None)``:
            the whole recording (an offset given, not estimated).
        label: what the estimate is of (:data:`uavcal_jax.data.true_offset.LABELS`):
            ``"total"`` (the whole constant error: an offset plus the sensor's own bias) or
            ``"injected"`` (an offset alone, what a calibrator trained on that label predicts).
        settings: the configuration the estimate ran with, a dataclass tree (resolved against
            the recording where a method resolves one), for ``OUT.config.json``.
        info: JSON-ready facts of the method (counts, the model, ...), for the summary.
        sigma: ``(C,)`` the standard deviation of ``median``'s error in its channels, the
            items' correlation accounted for
            (:func:`uavcal_jax.pipeline.offset_uncertainty.recording_sigma`), or ``None``
            for a method that cannot tell; ``inf`` where a channel is not determined.
    """

    offset: np.ndarray
    channels: tuple[str, ...]
    median: np.ndarray
    per_item: np.ndarray
    item_t_s: np.ndarray
    item: str
    span_ns: tuple[int, int]
    label: str
    settings: Any
    info: dict = field(default_factory=dict)
    sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS}, got {self.label!r}")
        if not set(self.channels) <= set(SIX_CHANNELS):
            raise ValueError(f"channels must be among {SIX_CHANNELS}, got {self.channels}")
        c = len(self.channels)
        if (np.shape(self.offset) != (6,) or np.shape(self.median) != (c,)
                or np.ndim(self.per_item) != 2 or np.shape(self.per_item)[1] != c
                or np.shape(self.item_t_s) != (np.shape(self.per_item)[0],)):
            raise ValueError("offset must be (6,), median (C,), per_item (N, C) and item_t_s "
                             f"(N,) for C = {c} channels")
        if self.sigma is not None and (np.shape(self.sigma) != (c,)
                                       or np.any(~(np.asarray(self.sigma) > 0.0))):
            raise ValueError(f"sigma must be (C,) = ({c},) positive numbers (inf: not "
                             f"determined), got {np.asarray(self.sigma).tolist()}")

    @property
    def channel_index(self) -> np.ndarray:
        """``(C,)`` where :attr:`channels` sit in a ``(6,)`` offset."""
        return np.array([SIX_CHANNELS.index(c) for c in self.channels], np.int64)


@dataclass(frozen=True)
class OffsetMethod:
    """An offset estimator as the registry holds it
    (:mod:`uavcal_jax.pipeline.offset_estimators`).

    Attributes:
        name: the registry key (``uavcal calib predict --method NAME``).
        summary: one line for ``--help``: what it does and what it needs.
        configure: ``configure(overrides, **arguments) -> options``: the method's options from
            ``key=value`` overrides (``--set``; :func:`uavcal_jax.config.apply_overrides`) and
            the keyword ``arguments`` it takes (raises
            :class:`~uavcal_jax.errors.DataError` on a bad one).
        estimate: ``estimate(sequence, options, *, progress=False) -> OffsetEstimate``; the
            sequence has no ground truth; ``progress``: progress bars on stderr.
        arguments: the keyword arguments ``configure`` takes besides the overrides (e.g.
            ``checkpoint``); a caller giving another one is refused
            (:func:`~uavcal_jax.pipeline.offset_estimators.configure_method`).
    """

    name: str
    summary: str
    configure: Callable[..., Any]
    estimate: Callable[..., OffsetEstimate]
    arguments: tuple[str, ...] = ()


def check_sequence(sequence: Sequence) -> None:
    """Refuse a sequence that still carries ground truth: estimators never see it."""
    if sequence.ground_truth is not None:
        raise ValueError(f"{sequence.name}: an offset estimator is given the recording without "
                         "its ground truth (strip it: dataclasses.replace(sequence, "
                         "ground_truth=None))")
