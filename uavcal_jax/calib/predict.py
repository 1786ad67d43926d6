"""Offset estimates over a whole sequence from a trained calibrator.

:func:`predict_sequence` cuts nothing itself: it takes a sequence's
:class:`~uavcal_jax.data.windows.WindowSet` (windows of the run's geometry), encodes each of
its frames once (:func:`uavcal_jax.calib.inference.encode_frames`, the frame-token reuse of
overlapping windows), predicts every window's offset, and summarises them by the median over
windows (robust to the few windows a fast manoeuvre or a dark stretch throws off). A run of
``K`` vmapped seeds is an ensemble: each window's estimate is the mean of the seeds'.

:func:`predict_on_sequence` does it for a run folder and a
:class:`~uavcal_jax.data.sequence.Sequence` (the ``transformer`` offset method,
:mod:`uavcal_jax.pipeline.transformer_offset`, which is scored against the truth by
:func:`uavcal_jax.pipeline.predict_offset.score`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.calib.batch import frames_to_model, model_imu
from uavcal_jax.calib.config import CalibRunConfig
from uavcal_jax.calib.data import Windows, mask_black_frames
from uavcal_jax.calib.inference import encode_frames, predict_windows
from uavcal_jax.calib.inject import inject
from uavcal_jax.calib.loop import first_seed, read_run_config, restore_run
from uavcal_jax.calib.model import split_prediction
from uavcal_jax.calib.train import CalibState, shifted_accel_start
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.data.windows import WindowSet, make_windows
from uavcal_jax.errors import DataError

__all__ = ["SequencePrediction", "channel_names", "expand_to_six", "model_channels",
           "mounting_angle_deg",
           "predict_on_sequence", "predict_sequence"]

GYRO_CHANNELS = ("gx", "gy", "gz")
ACCEL_CHANNELS = ("ax", "ay", "az")
#: Windows per predict call (one compile; the last call padded).
WINDOW_CHUNK = 32


class SequencePrediction(NamedTuple):
    """Offsets predicted over one sequence.

    Attributes:
        per_window: ``(W, C)`` each window's estimate (mean over seeds), gyro rad/s then
            accel m/s^2 (``C`` = 6, or 3 for a single-sensor model).
        per_seed: ``(K, W, C)`` each seed's estimates.
        start_s: ``(W,)`` window start times, seconds since the first frame.
        median: ``(C,)`` the median of ``per_window`` over windows: the sequence's estimate.
        channels: the names of the ``C`` channels.
        start_ns: ``(W,)`` int64 window start times, ns (the recording's clock).
        per_window_sigma: ``(W, C)`` each window's predicted uncertainty (the standard
            deviation of its estimate's error; over seeds, the root of the mean variance
            plus the seeds' spread), for a model with ``ModelConfig.variance``; else
            ``None``.
    """

    per_window: np.ndarray
    per_seed: np.ndarray
    start_s: np.ndarray
    median: np.ndarray
    channels: tuple[str, ...]
    start_ns: np.ndarray | None = None
    per_window_sigma: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray | None:
        """``(C,)`` the median over windows of :attr:`per_window_sigma` (``None`` without)."""
        return None if self.per_window_sigma is None else np.median(self.per_window_sigma,
                                                                    axis=0)


def channel_names(channels: int, sensor: str) -> tuple[str, ...]:
    """Names of a model's ``channels`` (6, or 3 of ``sensor``)."""
    if channels == 6:
        return GYRO_CHANNELS + ACCEL_CHANNELS
    return GYRO_CHANNELS if sensor == "gyro" else ACCEL_CHANNELS


def model_channels(channels: int, sensor: str) -> slice:
    """Where a model's ``channels`` (6, or 3 of ``sensor``) sit in a ``(6,)`` offset."""
    if channels == 6:
        return slice(0, 6)
    return slice(0, 3) if sensor == "gyro" else slice(3, 6)


def expand_to_six(offset, sensor: str) -> np.ndarray:
    """A ``(6,)`` offset from a 6- or 3-channel one (the other sensor's channels 0)."""
    offset = np.asarray(offset, np.float64).reshape(-1)
    out = np.zeros(6)
    out[model_channels(offset.size, sensor)] = offset
    return out


def _seed_states(state: CalibState, seeds: int) -> list[CalibState]:
    if seeds == 1:
        return [state]
    return [jax.tree.map(lambda x, k=k: x[k], state) for k in range(seeds)]


def predict_sequence(state: CalibState, windows: WindowSet, seeds: int = 1,
                     inject_offset=None) -> SequencePrediction:
    """Every window's offset estimate on ``windows`` (cut with the run's window geometry).

    Args:
        state: a restored :class:`CalibState` (stacked on a leading ``K`` axis when
            ``seeds > 1``).
        windows: the sequence's windows.
        seeds: ``K``.
        inject_offset: ``(C,)`` added to the recorded IMU before prediction (to try the model
            on a clean recording with a known miscalibration), or ``None``.

    Raises:
        DataError: the sequence has no window.
    """
    if len(windows) == 0:
        raise DataError("the sequence has no complete window", windows.name)
    config = _seed_states(state, seeds)[0].config
    model_cfg, sensor = config.model, config.injection.single_sensor
    all_idx = np.arange(len(windows))
    samples = windows.samples()
    imu = jnp.asarray(model_imu(samples, model_cfg, sensor))
    mask = jnp.asarray(samples["mask"], bool)
    if inject_offset is not None:
        offset = jnp.asarray(np.broadcast_to(np.asarray(inject_offset, np.float32),
                                             (len(all_idx), imu.shape[-1])))
        imu = inject(imu, offset, mask)
    frames = frames_to_model(windows.frames, model_cfg.rgb) if model_cfg.use_video else None
    index = np.asarray(windows.frame_index)
    motion = None
    if model_cfg.motion_tokens:
        motion = windows.motion(all_idx)
        if inject_offset is not None:  # the same gyro offset in every full-rate sample
            offset = np.asarray(inject_offset, np.float32).reshape(-1)
            motion["gyro_seq"] = motion["gyro_seq"] + offset[:3]
            if "accel_start" in motion and offset.size == 6:  # the alignment moves with it
                motion["accel_start"] = np.asarray(shifted_accel_start(
                    motion["accel_start"], motion["accel_response"],
                    np.broadcast_to(offset, (len(all_idx), 6))))
    per_seed, per_seed_log_sigma = [], []
    for s in _seed_states(state, seeds):
        tokens = None if frames is None else encode_frames(s.model, s.variables(), frames)
        out = []
        for lo in range(0, len(all_idx), WINDOW_CHUNK):
            sel = np.arange(lo, lo + WINDOW_CHUNK).clip(max=len(all_idx) - 1)
            part = None if motion is None else {k: v[sel] for k, v in motion.items()}
            out.append(np.asarray(predict_windows(s.model, s.variables(), tokens, index[sel],
                                                  mask[sel], imu[sel], part)))
        offsets, log_sigma = split_prediction(np.concatenate(out)[:len(all_idx)], model_cfg)
        per_seed.append(offsets)
        per_seed_log_sigma.append(log_sigma)
    per_seed_arr = np.stack(per_seed).astype(np.float64)
    per_window = per_seed_arr.mean(axis=0)
    sigma = None
    if model_cfg.variance:  # the seeds as a mixture: mean variance plus their spread
        variance = np.exp(2.0 * np.stack(per_seed_log_sigma).astype(np.float64))
        sigma = np.sqrt(variance.mean(axis=0) + per_seed_arr.var(axis=0))
    start_s = (windows.start_ns - windows.frame_t_ns[0]) * 1e-9
    return SequencePrediction(per_window, per_seed_arr, start_s, np.median(per_window, axis=0),
                              channel_names(per_window.shape[1], sensor),
                              np.asarray(windows.start_ns, np.int64), sigma)


def mounting_angle_deg(accel: np.ndarray, training_mean: np.ndarray) -> float:
    """Degrees between a recording's mean specific force (``accel (N, 3)`` m/s^2, IMU frame:
    gravity's reaction, flight accelerations averaging out) and a calibrator's training mean
    (3,): about 0 for an IMU mounted as in the training flights, 90 for one turned a quarter
    (gravity on z rather than EuRoC's x)."""
    a = np.mean(np.asarray(accel, np.float64).reshape(-1, 3), axis=0)
    b = np.asarray(training_mean, np.float64).reshape(3)
    cos = a @ b / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def predict_on_sequence(run_dir: str | Path, sequence: Sequence, *, kind: str = "best",
                        run: CalibRunConfig | None = None, inject_offset=None,
                        rotation_source: Callable[[Sequence], Any] | None = None,
                        pose_source: Callable[[Sequence], Any] | None = None
                        ) -> tuple[dict, SequencePrediction]:
    """``(info, prediction)`` of the run folder's ``kind`` checkpoint on ``sequence``, cut into
    the run's windows (black frames masked, as in training). Reads nothing of the recording
    but ``sequence`` (its ground truth, when it has one, is not used).

    ``run``: the configuration to predict under (default the run's own,
    :func:`~uavcal_jax.calib.loop.read_run_config`; a command's ``--set`` may change what a
    restored model allows, :data:`~uavcal_jax.calib.loop.INFERENCE_KEYS`, e.g.
    ``model.frame_encoder_dtype``: the frame encoder's operand type, same parameters).
    ``inject_offset``: ``(6,)`` added to the IMU first (only the model's channels are used).
    ``rotation_source``: for a run with ``window.rotations=visual``, ``rotation_source(
    sequence)`` the camera's relative rotations of the sequence
    (:func:`uavcal_jax.pipeline.motion_inputs.sequence_rotations`: calib may not import the
    VIO); ``window.rotations=oracle`` reads the sequence's ground truth. ``pose_source``: for
    a run with ``window.accel_start=alignment``, ``pose_source(sequence)`` its VIO trajectory
    (:func:`uavcal_jax.pipeline.motion_inputs.sequence_poses`).
    ``info`` (JSON-ready): ``run``, ``kind``, ``seeds``, ``sensor``, ``channels``,
    ``frame_encoder_dtype``, ``window_s``, ``stride_s``, ``windows``.

    Raises:
        DataError: not a run folder, a checkpoint of another configuration or version, a
            sequence shorter than one window.
    """
    run = read_run_config(run_dir) if run is None else run
    window = run.window
    sensor = run.injection.single_sensor
    where = sequence.root if sequence.root is not None else sequence.name
    inputs = {}  # the motion inputs the window configuration asks for, from their sources
    for needed, key, source, name, what in (
            (window.rotations == "visual", "visual_rotations", rotation_source,
             "rotation_source", "window.rotations=visual needs the recording's visual "
             "rotations"),
            (window.accel_start == "alignment", "vio_poses", pose_source, "pose_source",
             "window.accel_start=alignment needs the recording's VIO poses")):
        if needed:
            if source is None:
                raise DataError(f"{what} (predict_on_sequence's {name})", where)
            inputs[key] = source(sequence)
    ws = mask_black_frames(make_windows(sequence, window, **inputs), where)
    part = Windows(ws, np.arange(len(ws)), str(where))
    state, seeds = restore_run(run_dir, [part], kind=kind, run=run)
    pick = model_channels(run.model.imu_channels, sensor)
    shift = None if inject_offset is None else np.asarray(inject_offset, np.float64)[pick]
    prediction = predict_sequence(state, part.windows, seeds, inject_offset=shift)
    train_mean = np.asarray(jax.device_get(first_seed(state, seeds).imu_stats.mean))
    # a model trained with random mountings has no training mounting to compare with
    angle = (None if train_mean.shape[-1] != 6 or sequence.imu is None
             or run.train.mounting == "random" else
             mounting_angle_deg(sequence.imu.accel, train_mean[3:]))
    info = {
        "run": str(run_dir), "kind": kind, "seeds": seeds, "sensor": sensor,
        "gravity_angle_deg": angle,
        "training_specific_force": None if angle is None else train_mean[3:].tolist(),
        "channels": list(prediction.channels),
        "frame_encoder_dtype": state.config.model.frame_encoder_dtype,
        "window_s": window.duration, "stride_s": window.stride,
        "windows": int(prediction.per_window.shape[0]),
    }
    return info, prediction
