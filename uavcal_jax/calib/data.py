"""Sequences to windows to model batches for the calibrator's training loop and CLI.

- :func:`find_sequences` / :func:`load_windows`: EuRoC folders (real or simulated, or a folder
  of them) cut into :class:`~uavcal_jax.data.windows.WindowSet` s. Bad input: a sequence
  shorter than one window is a :class:`~uavcal_jax.errors.DataError` (from ``make_windows``);
  NaN/inf IMU rows are dropped by the EuRoC reader with a warning; **all-black frames** (every
  pixel 0: a dead or covered camera) are treated as missing frames -- their slots are masked
  like dropped frames (zero pixels and IMU values, ``mask`` false), with one
  :class:`~uavcal_jax.errors.DataRepairWarning`; a sequence whose frames are all black is an
  error.
- :class:`Windows`: some windows of one set (``indices``); :func:`as_windows` normalises what
  :func:`uavcal_jax.calib.loop.fit` is given (a WindowSet, a ``Windows`` or a list of them).
- :func:`gather`: model inputs (:func:`uavcal_jax.calib.batch.model_batch`) of windows picked
  by flat index over a list of ``Windows``, padded to a fixed batch with ``weight`` 0 rows so
  that the last short batch does not cost a new compile.
- Validation schemes (``loop.validation``): :func:`split_windows` (the fixed random split
  over windows), :func:`leave_one_out` (one trial per sequence) and :func:`kfold_windows`
  (contiguous blocks of windows, so overlapping neighbours mostly stay on one side).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from uavcal_jax.calib.batch import model_batch
from uavcal_jax.calib.config import ModelConfig
from uavcal_jax.calib.inject import ImuStats, imu_statistics, window_samples
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.windows import WindowConfig, WindowSet, make_windows
from uavcal_jax.errors import DataError, DataRepairWarning

__all__ = ["Windows", "as_windows", "count_windows", "find_sequences", "gather", "kfold_windows",
           "label_channels", "leave_one_out", "load_windows", "mask_black_frames",
           "mean_sensor_bias", "split_windows", "training_statistics"]


class Windows(NamedTuple):
    """Windows ``indices (n,)`` of ``windows``; ``source`` is the sequence folder (or name)."""

    windows: WindowSet
    indices: np.ndarray
    source: str


def as_windows(data) -> list[Windows]:
    """A list of :class:`Windows` from a WindowSet, a Windows, or a sequence of either
    (``None``: empty)."""
    if data is None:
        return []
    if isinstance(data, WindowSet | Windows):
        data = [data]
    out = []
    for d in data:
        if isinstance(d, WindowSet):
            d = Windows(d, np.arange(len(d)), d.name)
        out.append(Windows(d.windows, np.asarray(d.indices, np.int64), d.source))
    shapes = {(w.windows.frames_per_window,) + w.windows.frames.shape[1:] for w in out}
    if len(shapes) > 1:
        raise DataError(f"windows of different shapes (frames per window, frame size) cannot "
                        f"share batches: {sorted(shapes)}; use one camera rate and size")
    return out


def find_sequences(dirs: Sequence[str | Path]) -> list[Path]:
    """EuRoC sequence folders: each of ``dirs`` that holds ``mav0`` (or is one), else its
    sub-folders that do, sorted by name."""
    found: list[Path] = []
    for d in map(Path, dirs):
        if not d.is_dir():
            raise DataError("no such folder", d)
        if d.name == "mav0" or (d / "mav0").is_dir():
            found.append(d)
            continue
        kids = sorted(p for p in d.iterdir() if p.is_dir() and (p / "mav0").is_dir())
        if not kids:
            raise DataError("neither a EuRoC sequence (mav0/) nor a folder of them", d)
        found += kids
    return found


def mask_black_frames(ws: WindowSet, where: str | Path) -> WindowSet:
    """``ws`` with all-black frames treated as missing (see the module docstring)."""
    black = ws.frames.reshape(ws.frames.shape[0], -1).max(axis=1) == 0
    if not black.any():
        return ws
    if black.all():
        raise DataError(f"all {black.size} frames are black (every pixel 0)", where)
    hit = ws.frame_mask & black[np.maximum(ws.frame_index, 0)]
    warnings.warn(DataRepairWarning(f"{where}: {int(black.sum())} all-black frames treated as "
                                    "missing (masked out of their windows)"), stacklevel=2)
    return dataclasses.replace(ws, frame_mask=ws.frame_mask & ~hit,
                               frame_index=np.where(hit, -1, ws.frame_index).astype(np.int32))


def load_windows(dirs: Sequence[str | Path], config: WindowConfig,
                 rotation_source: Callable[[Path], Any] | None = None,
                 pose_source: Callable[[Path], Any] | None = None) -> list[Windows]:
    """Every window of every sequence found under ``dirs`` (:func:`find_sequences`).

    ``rotation_source``: under ``config.rotations == "visual"``, a callable ``(folder) ->``
    the recording's relative camera rotations (a ``VisualRotations``-like tuple, see
    :func:`~uavcal_jax.data.windows.make_windows`); ``pose_source``: under
    ``config.accel_start == "alignment"``, ``(folder) ->`` its VIO trajectory. The caller
    supplies them (calib does not import the VIO):
    :func:`uavcal_jax.pipeline.motion_inputs.folder_sources`."""
    if config.rotations == "visual" and rotation_source is None:
        raise DataError("window.rotations=visual needs a source of the camera's relative "
                        "rotations (load_windows' rotation_source)")
    if config.accel_start == "alignment" and pose_source is None:
        raise DataError("window.accel_start=alignment needs a source of the VIO's poses "
                        "(load_windows' pose_source)")
    out = []
    for root in find_sequences(dirs):
        visual = rotation_source(Path(root)) if config.rotations == "visual" else None
        poses = pose_source(Path(root)) if config.accel_start == "alignment" else None
        ws = mask_black_frames(make_windows(read_euroc(root), config, visual_rotations=visual,
                                            vio_poses=poses), root)
        out.append(Windows(ws, np.arange(len(ws)), str(Path(root).absolute())))
    return out


def _locate(parts: list[Windows]) -> tuple[np.ndarray, np.ndarray]:
    src = np.concatenate([np.full(len(p.indices), j) for j, p in enumerate(parts)])
    loc = np.concatenate([p.indices for p in parts])
    return src, loc


def gather(parts: list[Windows], flat: np.ndarray, model: ModelConfig, sensor: str,
           batch_size: int | None = None, label: str = "injected", tilt: bool = True) -> dict:
    """Model inputs of windows ``flat`` (indices into the concatenation of ``parts``), with
    ``weight (B,)``: 1 for real windows, 0 for the copies of the first one that pad the batch
    to ``batch_size``. Under the ``total`` label (``InjectionConfig.target``) also ``bias
    (B, C)`` float32: the sensor's own bias over each window, the label's share besides the
    injected offset (:func:`label_channels` of ``WindowSet.sensor_bias``). With
    ``model.motion_tokens`` also the interval inputs ``gyro_seq``, ``dt_seq``, ``rot_cam``,
    ``rot_mask`` (:meth:`~uavcal_jax.data.windows.WindowSet.motion`; ``S`` the largest
    :attr:`~uavcal_jax.data.windows.WindowSet.interval_cap` of ``parts``). With
    ``model.tilt_head`` and ``tilt`` also the tilt label ``up (B, T, 3)``
    (:meth:`~uavcal_jax.data.windows.WindowSet.up`; ``tilt=False`` for inputs alone)."""
    src, loc = _locate(parts)
    flat = np.asarray(flat, np.int64)
    n = flat.size
    pad = np.concatenate([flat, np.full(max(0, (batch_size or n) - n), flat[0])])
    rows = [parts[src[i]].windows.batch([loc[i]]) for i in pad]
    keys = ("frames", "mask", "gyro", "accel")
    wb = {k: np.concatenate([r[k] for r in rows]) for k in keys}
    out = model_batch(wb, model, sensor)
    out["weight"] = (np.arange(pad.size) < n).astype(np.float32)
    if model.motion_tokens:
        out.update(_motion(parts, src, loc, pad))
    if model.tilt_head and tilt:
        out["up"] = _up(parts, src, loc, pad)
    if label == "total":
        _require_bias(parts)
        bias = np.concatenate([r["sensor_bias"] for r in rows])
        out["bias"] = label_channels(bias, model.imu_channels, sensor).astype(np.float32)
    return out


def _motion(parts: list[Windows], src: np.ndarray, loc: np.ndarray, pad: np.ndarray) -> dict:
    for p in parts:
        if p.windows.frame_R is None:
            raise DataError("model.motion_tokens needs frame orientations: set "
                            "window.rotations=oracle or visual", p.source)
    cap = max(p.windows.interval_cap for p in parts)
    rows = [parts[src[i]].windows.motion([loc[i]], cap) for i in pad]
    return {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}


def _up(parts: list[Windows], src: np.ndarray, loc: np.ndarray, pad: np.ndarray) -> np.ndarray:
    for p in parts:
        if p.windows.frame_up is None:
            raise DataError("model.tilt_head learns from the ground truth's orientation; this "
                            "recording has no ground truth", p.source)
    return np.concatenate([parts[src[i]].windows.up([loc[i]]) for i in pad])


def label_channels(six: np.ndarray, channels: int, sensor: str) -> np.ndarray:
    """The model's channels of ``(..., 6)`` values (gyro then accel): all six, or the three
    of ``sensor`` for a 3-channel model."""
    if channels == 6:
        return six
    return six[..., :3] if sensor == "gyro" else six[..., 3:]


def _require_bias(parts: list[Windows]) -> None:
    for p in parts:
        if p.windows.sensor_bias is None:
            raise DataError("the total label needs the recording's ground-truth bias columns "
                            "(state_groundtruth_estimate0 with b_w/b_a); this one has none: "
                            "set injection.label=injected", p.source)


def mean_sensor_bias(parts: list[Windows], channels: int, sensor: str) -> np.ndarray:
    """``(C,)`` the mean sensor bias over the chosen windows of ``parts`` (the ``total``
    label's share that a no-learning estimate can take from the training set)."""
    _require_bias(parts)
    bias = np.concatenate([p.windows.sensor_bias[p.indices] for p in parts])
    return label_channels(bias.mean(axis=0), channels, sensor)


def training_statistics(parts: list[Windows], channels: int, sensor: str) -> ImuStats:
    """Per-channel IMU mean/std over every sample inside the chosen windows (the paper
    protocol's ``mu``, ``sigma``); 3 channels: those of ``sensor``."""
    samples = []
    for p in parts:
        imu = window_samples(p.windows, p.indices)
        if channels == 3:
            imu = imu[:, :3] if sensor == "gyro" else imu[:, 3:]
        samples.append(imu)
    return imu_statistics(np.concatenate(samples))


def count_windows(parts: Iterable[Windows]) -> int:
    """Windows in ``parts`` (the sum of their ``indices``' lengths)."""
    return int(sum(len(p.indices) for p in parts))


def _select(parts: list[Windows], flat: np.ndarray) -> list[Windows]:
    """The windows ``flat`` (sorted) of ``parts``, grouped back by set."""
    src, loc = _locate(parts)
    flat = np.sort(np.asarray(flat, np.int64))
    return [Windows(p.windows, loc[flat[src[flat] == j]], p.source)
            for j, p in enumerate(parts) if np.any(src[flat] == j)]


def split_windows(parts: list[Windows], val_fraction: float, seed: int
                  ) -> list[tuple[list[Windows], list[Windows]]]:
    """One trial: a fixed random ``val_fraction`` of all windows for validation (the
    ablation's 80/20 split; overlapping windows share frames across it)."""
    n = count_windows(parts)
    n_val = int(round(val_fraction * n))
    if n_val < 1 or n_val >= n:
        raise DataError(f"a {val_fraction:g} validation split of {n} windows leaves a side "
                        "empty; give more data or another fraction")
    order = np.random.default_rng(seed).permutation(n)
    return [(_select(parts, order[n_val:]), _select(parts, order[:n_val]))]


def leave_one_out(parts: list[Windows]) -> list[tuple[list[Windows], list[Windows]]]:
    """One trial per sequence: validate on it, train on the others."""
    if len(parts) < 2:
        raise DataError(f"leave-one-sequence-out needs at least 2 sequences, got {len(parts)}")
    return [([q for j, q in enumerate(parts) if j != i], [p]) for i, p in enumerate(parts)]


def kfold_windows(parts: list[Windows], folds: int) -> list[tuple[list[Windows], list[Windows]]]:
    """``folds`` trials over contiguous blocks of the concatenated windows."""
    n = count_windows(parts)
    if not 2 <= folds <= n:
        raise DataError(f"{folds}-fold validation needs 2 <= folds <= windows ({n})")
    blocks = np.array_split(np.arange(n), folds)
    return [(_select(parts, np.setdiff1d(np.arange(n), b)), _select(parts, b)) for b in blocks]
