"""``transformer``: the IMU offset from a trained calibrator (Avola et al. 2023;
:mod:`uavcal_jax.calib`).

The recording is cut into the run's windows, every window gets the model's estimate, and the
median over windows is the recording's (:func:`uavcal_jax.calib.predict.predict_on_sequence`).
Its standard deviation (for a model with an uncertainty head, ``model.variance``) is the
windows' batch-means standard error, one block per window length, with what the windows
share: the model's median window sigma times the run's measured common scale
(:data:`UNCERTAINTY_FILE`, :func:`common_scale`).
What it estimates is what it was trained to predict: the run's label in force
(:attr:`uavcal_jax.calib.config.InjectionConfig.target`). An IMU mounted otherwise than in
the training flights (gravity past :data:`MOUNTING_TOLERANCE_DEG` from theirs) is tilted into
their mounting for the model, and the estimate turned back (:func:`mounting_alignment`).
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.calib.config import CalibRunConfig
from uavcal_jax.calib.loop import read_run_config
from uavcal_jax.calib.predict import expand_to_six, predict_on_sequence
from uavcal_jax.calib.presets import resolve_configs
from uavcal_jax.calib.pretrained import default_weights
from uavcal_jax.calib.trials import TRIAL_FORMAT, trial_folders
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError, OutOfDomainWarning
from uavcal_jax.pipeline.motion_inputs import sequence_poses, sequence_rotations, sequence_sources
from uavcal_jax.pipeline.offset_estimate import (
    SIX_CHANNELS,
    OffsetEstimate,
    OffsetMethod,
    check_sequence,
)
from uavcal_jax.pipeline.offset_uncertainty import recording_sigma

__all__ = ["METHOD", "MOUNTING_TOLERANCE_DEG", "UNCERTAINTY_FILE", "TransformerOptions",
           "TransformerSettings", "common_scale", "configure", "estimate", "mounting_alignment",
           "run_folder", "write_common_scale"]

#: The file in a run folder holding its measured common scale (:func:`common_scale`).
UNCERTAINTY_FILE = "uncertainty.json"


def common_scale(run_dir: str | Path, channels) -> np.ndarray:
    """``(C,)`` the share of the model's median window sigma that a recording's windows have in
    common, per channel of ``channels``, as measured for the run (:data:`UNCERTAINTY_FILE`,
    written by ``experiments/calib_uncertainty.py``); 1 where it was not measured (the
    window sigma taken as wholly shared: no credit for averaging windows).

    Raises:
        DataError: the file is there but unreadable or malformed (named).
    """
    path = Path(run_dir) / UNCERTAINTY_FILE
    out = np.ones(len(channels))
    if not path.is_file():
        return out
    try:
        scales = json.loads(path.read_text())["common_scale"]
        for i, c in enumerate(channels):
            if c in scales:
                out[i] = float(scales[c])
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"not an uncertainty file ({type(exc).__name__}: {exc}); expected "
                        '{"common_scale": {"gx": K, ...}}', path) from exc
    if not np.all(np.isfinite(out) & (out >= 0.0)):
        raise DataError(f"common_scale must be finite and >= 0, got {out.tolist()}", path)
    return out


def write_common_scale(run_dir: str | Path, scales: dict[str, float], facts: dict) -> Path:
    """Write ``scales`` (channel -> k) and the ``facts`` of their measurement to the run's
    :data:`UNCERTAINTY_FILE`, atomically."""
    path = Path(run_dir) / UNCERTAINTY_FILE
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps({"common_scale": scales, **facts}, indent=1) + "\n")
    tmp.replace(path)
    return path


@dataclass(frozen=True)
class TransformerOptions:
    """The ``transformer`` method's options.

    Attributes:
        run_dir: the run folder (``calib train``'s output, or a loo/kfold trial folder).
        kind: its checkpoint: ``"best"`` or ``"last"``.
        run: the configuration to predict under: the run's own, with ``--set`` of what a
            restored model may change (:data:`uavcal_jax.calib.loop.INFERENCE_KEYS`).
    """

    run_dir: Path
    kind: str
    run: CalibRunConfig


@dataclass(frozen=True)
class TransformerSettings:
    """What :func:`configure` takes besides ``--set``, as a config tree holds it (``uavcal run
    --set offset.transformer.*``): the run folder and its checkpoint are read at run time.

    Attributes:
        checkpoint: the run folder (``None``: the shipped weights, :func:`run_folder`).
        kind: its checkpoint, ``"best"`` or ``"last"``.
        frame_dtype: the frame encoder's operand type (``model.frame_encoder_dtype``;
            ``None``: the run's).
    """

    checkpoint: str | None = None
    kind: str = "best"
    frame_dtype: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("best", "last"):
            raise ValueError(f"kind must be 'best' or 'last', got {self.kind!r}")


def run_folder(checkpoint: str | Path | None) -> Path:
    """The run folder to predict with: ``checkpoint``, or the shipped weights when ``None``
    (:func:`uavcal_jax.calib.pretrained.default_weights`).

    Raises:
        DataError: ``checkpoint`` holds one model per trial (a loo/kfold run), not one.
    """
    if checkpoint is None:
        return default_weights()
    run = Path(checkpoint)
    if not (run / "config.json").is_file() and trial_folders(run):
        raise DataError("a loo/kfold run holds one model per trial: give one, e.g. "
                        f"{run / TRIAL_FORMAT.format(0)}", run)
    return run


def configure(overrides: Iterable[str] = (), *, checkpoint: str | Path | None = None,
              kind: str | None = None, frame_dtype: str | None = None) -> TransformerOptions:
    """:class:`TransformerOptions` of the run folder ``checkpoint`` (default the shipped
    weights), its checkpoint ``kind`` (default ``"best"``), with ``overrides`` and
    ``frame_dtype`` (``model.frame_encoder_dtype``; ``None``: the run's) applied to the run's
    configuration.

    Raises:
        DataError: not a run folder; an unknown key or one a restored model may not change
            (named).
    """
    run_dir = run_folder(checkpoint)
    run = resolve_configs(list(overrides), preset=read_run_config(run_dir),
                          arguments={"model.frame_encoder_dtype": frame_dtype})
    return TransformerOptions(run_dir, "best" if kind is None else kind, run)


def estimate(sequence: Sequence, options: TransformerOptions, *,
             progress: bool = False) -> OffsetEstimate:
    """The ``transformer`` estimate of ``sequence`` (no ground truth). ``info`` holds the
    run, checkpoint kind, seeds, sensor, frame encoder dtype and the windows' geometry and
    count (:func:`~uavcal_jax.calib.predict.predict_on_sequence`). ``progress`` is unused:
    the prediction is seconds.

    Raises:
        DataError: see :func:`~uavcal_jax.calib.predict.predict_on_sequence`.
    """
    check_sequence(sequence)
    run = options.run
    if run.window.rotations == "oracle":
        raise DataError("this run reads ground-truth rotations (window.rotations=oracle): a "
                        "bound for tables, not an estimate without ground truth",
                        options.run_dir)
    info, prediction = predict_on_sequence(options.run_dir, sequence, kind=options.kind,
                                           run=run, **sequence_sources(run.window))
    angle = info.get("gravity_angle_deg")
    if angle is not None and angle > MOUNTING_TOLERANCE_DEG:
        info, prediction = _predict_remounted(sequence, options, info, prediction)
    sigma = None
    if prediction.per_window_sigma is not None:  # a model with an uncertainty (model.variance)
        common = common_scale(options.run_dir, prediction.channels) * prediction.sigma
        sigma = np.maximum(recording_sigma(prediction.per_window, prediction.start_s,
                                           run.window.duration, common=common),
                           np.finfo(np.float64).tiny)
        info = {**info, "window_sigma_median": prediction.sigma.tolist()}
    duration_ns = int(round(run.window.duration * 1e9))
    start_ns = prediction.start_ns
    return OffsetEstimate(
        offset=expand_to_six(prediction.median, run.injection.single_sensor),
        channels=tuple(prediction.channels), median=np.asarray(prediction.median, np.float64),
        per_item=np.asarray(prediction.per_window, np.float64),
        item_t_s=np.asarray(prediction.start_s, np.float64), item="window",
        span_ns=(int(start_ns[0]), int(start_ns[-1]) + duration_ns - 1),
        label=run.injection.target, settings=run, info=info, sigma=sigma)


def mounting_alignment(accel: np.ndarray, training_specific_force) -> np.ndarray:
    """(3, 3) the smallest rotation taking a recording's mean specific force (``accel (N, 3)``
    m/s^2, IMU frame) onto the direction of a calibrator's training mean (3,): applied to the
    IMU's vectors (``v' = R v``) it tilts an IMU mounted otherwise back into the training
    flights' mounting, up to a turn about gravity, which the specific force cannot see."""
    a = np.mean(np.asarray(accel, np.float64).reshape(-1, 3), axis=0)
    b = np.asarray(training_specific_force, np.float64).reshape(3)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(a @ b)
    if sin < 1e-12:  # parallel (nothing to do) or opposite (any perpendicular axis)
        if cos > 0:
            return np.eye(3)
        axis = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
        sin = np.linalg.norm(axis)
    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()


def _rotate_channels(values: np.ndarray, channels: list[str], R: np.ndarray) -> np.ndarray:
    """``values (..., C)`` in ``channels`` (whole gyro and/or accel triplets), each triplet
    turned by ``R`` (3, 3)."""
    out = np.array(values, np.float64)
    for first in (0, 3):
        names = list(SIX_CHANNELS[first:first + 3])
        if names[0] in channels:
            at = [channels.index(n) for n in names]
            out[..., at] = out[..., at] @ R.T
    return out


def _predict_remounted(sequence: Sequence, options: TransformerOptions, info: dict,
                       prediction):
    """The prediction with the IMU tilted into the training flights' mounting
    (:func:`mounting_alignment`: its samples and the camera's relative body rotations turned
    into that frame), turned back into the recording's IMU frame (a model's channels are
    whole triplets: :func:`~uavcal_jax.calib.predict.channel_names`); a warning says so."""
    angle = info["gravity_angle_deg"]
    R = mounting_alignment(sequence.imu.accel, info["training_specific_force"])
    imu = dataclasses.replace(sequence.imu, gyro=sequence.imu.gyro @ R.T,
                              accel=sequence.imu.accel @ R.T)

    def turned_rotations(recording):
        visual = sequence_rotations(recording)
        return visual._replace(R=R @ visual.R @ R.T)

    def turned_poses(recording):  # the VIO runs on the recording as it is, then turns
        poses = sequence_poses(sequence)
        return poses._replace(rotation=poses.rotation @ R.T, bias_gyro=poses.bias_gyro @ R.T)

    sources = sequence_sources(options.run.window)
    turned_sources = {"rotation_source": sources["rotation_source"] and turned_rotations,
                      "pose_source": sources["pose_source"] and turned_poses}
    info, turned = predict_on_sequence(options.run_dir, dataclasses.replace(sequence, imu=imu),
                                       kind=options.kind, run=options.run, **turned_sources)
    back = R.T  # the estimate is in the turned frame
    channels = list(turned.channels)
    sigma = turned.per_window_sigma
    if sigma is not None:  # independent errors per channel: the variances turn by R^2
        sigma = np.sqrt(_rotate_channels(np.square(sigma), channels, np.square(back)))
    prediction = turned._replace(
        per_window=_rotate_channels(turned.per_window, channels, back),
        per_seed=_rotate_channels(turned.per_seed, channels, back),
        median=_rotate_channels(turned.median, channels, back), per_window_sigma=sigma)
    info = {**info, "gravity_angle_deg": angle,
            "mounting_alignment_deg": float(np.degrees(Rotation.from_matrix(R).magnitude()))}
    warnings.warn(OutOfDomainWarning(
        f"{sequence.name}: the IMU's mean specific force points {angle:.0f} degrees away from "
        "the calibrator's training flights' (an IMU mounted otherwise): the IMU was tilted "
        "into the training mounting for the model and its estimate turned back; a turn about "
        "gravity cannot be undone so, and vio-bias does not depend on the mounting"),
        stacklevel=3)
    return info, prediction


#: Degrees between a recording's mean specific force and the training flights' beyond which
#: the ``transformer`` tilts the IMU into the training mounting (a drone tilts 10-20 degrees on
#: average at most; another IMU mounting turns gravity by 90). The shipped weights with the
#: IMU turned a quarter (experiments/calib_blind.py --imu-rotation=0,-90,0 --methods
#: transformer): gyro 0.0007 rad/s and accelerometer 0.185 m/s^2 off, against 0.0072 and 0.85
#: fed the turned IMU as it is, 0.0006 and 0.090 as trained, 0.055 and 0.208 with no
#: correction. The accelerometer's part stays worse: the tilt is read off the mean specific
#: force, which holds the accelerometer's offset too, so the part of the offset across gravity
#: is turned away with the tilt (1 degree of tilt is 0.17 m/s^2).
MOUNTING_TOLERANCE_DEG = 30.0


METHOD = OffsetMethod(
    name="transformer", configure=configure, estimate=estimate,
    arguments=("checkpoint", "kind", "frame_dtype"),
    summary="a trained calibrator (--checkpoint RUN, default the shipped small weights): "
            "median over its windows; --set reaches the run's configuration (what a restored "
            "model may change)")
