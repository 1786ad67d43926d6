"""Hybrid recordings: a real IMU and ground truth under simulated stereo frames.

:func:`simulate_hybrid` reads a real recording (an EuRoC ASL folder or a bag: anything
:func:`uavcal_jax.data.read.read_sequence` reads, with an IMU and a ground truth whose body
frame is the IMU frame, as EuRoC's), fits the smooth trajectory to its ground truth
(:func:`uavcal_jax.sim.trajectory_fit.fit_tum_trajectory`) and renders the simulator's
cameras, depth and target labels along it (:func:`uavcal_jax.sim.frames.render_frames`: EuRoC's
stereo rig, whose ``T_BS`` are relative to that same IMU frame). The output is a simulated
recording (``out_dir/mav0`` and ``out_dir/sim_config.json``, as :mod:`uavcal_jax.sim.simulate`
writes) whose IMU and ground truth are the real ones:

- IMU: the real samples over the span, values and int64 timestamps unchanged (the EuRoC
  writer's round-trip ``repr`` gives back the same float64 values), plus
  ``SimConfig.imu_offset`` when one is set (added as the simulator adds it); ``imu0/sensor.yaml``
  has the real IMU's calibration (its noise densities and random walks).
- Ground truth: the real rows over the span, unchanged (their bias columns are then the real
  sensor's own constant error; EuRoC V1_01: about (-0.0022, 0.0211, 0.0765) rad/s).
- Frames: on the real camera clock. EuRoC's cameras are triggered on every
  ``imu_rate / camera_rate``-th IMU sample (every 10th at 200/20 Hz); the trigger's phase is
  taken from the real ``cam0`` timestamps (:func:`trigger_phase`), so the frames fall on real
  IMU timestamps, and the real frames' own timestamps are among them, over the whole span
  (not only where real frames exist).

Span: ``start`` seconds after the real IMU's first sample, moved forward to the next trigger
sample (so the recording starts with a frame, as the simulator's do), for ``duration`` seconds
of IMU samples, inside the time both the IMU and the ground truth cover.

``sim_config.json`` records ``flight.source = "hybrid"`` and the real folder, ``imu_noise: null``
(the noise is the real sensor's) and ``config.imu_offset`` (the injected offset, ``null`` for
none), so readers, ``uavcal calib predict`` and ``uavcal vio`` treat the output as any simulated
recording whose ground truth carries the real biases.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from uavcal_jax import __version__
from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.data.euroc_writer import EurocWriter
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sequence import GroundTruth, ImuData, Sequence
from uavcal_jax.data.sim_config import SIM_CONFIG_FILE
from uavcal_jax.errors import DataError
from uavcal_jax.sim.config import (
    IDEAL_SENSORS,
    IMU_ERRORS,
    SimConfig,
    camera_calibrations,
    stage_seeds,
)
from uavcal_jax.sim.simulate import (
    SimReport,
    calib_dict,
    check_out_dir,
    finish_report,
    render_into_report,
    with_offset,
    write_recording_atomically,
)
from uavcal_jax.sim.trajectory_fit import fit_tum_trajectory

__all__ = ["HybridSpan", "hybrid_span", "read_real", "simulate_hybrid", "trigger_phase"]

#: SimConfig's defaults (the simulated IMU errors at their defaults are turned off here).
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(SimConfig)}

#: A ground-truth row belongs to the span when it lies within this of the span's first/last
#: IMU sample: EuRoC's ground-truth clock sits up to 256 ns off the IMU samples it was
#: estimated at (float64 seconds in its pipeline); far below half an IMU period.
GT_TOLERANCE_NS = 1_000_000


@dataclasses.dataclass(frozen=True)
class HybridSpan:
    """The part of a real recording a hybrid covers.

    Attributes:
        imu: slice of the real IMU's sample indices.
        cam_t_ns: (F,) int64 frame timestamps: the trigger samples in the span.
        gt: (G,) bool mask of the real ground-truth rows in the span.
        phase: index (mod ``ratio``) of the trigger samples among the real IMU samples.
        phase_from: ``"cam0"`` (the real frames' timestamps) or ``"imu"`` (none usable: the
            trigger is the span's first sample).
        ratio: IMU samples per frame.
    """

    imu: slice
    cam_t_ns: np.ndarray
    gt: np.ndarray
    phase: int
    phase_from: str
    ratio: int


def trigger_phase(imu_t_ns: np.ndarray, cam_t_ns: np.ndarray, ratio: int) -> int | None:
    """The index residue (mod ``ratio``) of the IMU samples the camera is triggered on: every
    camera timestamp must be an IMU timestamp, all at the same residue; ``None`` otherwise (no
    frames, or a camera not triggered by the IMU).

    Args:
        imu_t_ns: (N,) int64 increasing IMU timestamps.
        cam_t_ns: (F,) int64 camera timestamps.
        ratio: IMU samples per frame.
    """
    cam_t_ns = np.asarray(cam_t_ns, np.int64)
    if cam_t_ns.size == 0:
        return None
    idx = np.searchsorted(imu_t_ns, cam_t_ns)
    inside = idx < len(imu_t_ns)
    if not inside.all() or np.any(imu_t_ns[idx] != cam_t_ns):
        return None
    residues = np.unique(idx % ratio)
    return int(residues[0]) if residues.size == 1 else None


def hybrid_span(real: Sequence, start: float, duration: float, ratio: int,
                where: Path | None = None) -> HybridSpan:
    """Choose the real IMU samples, frame timestamps and ground-truth rows of a hybrid.

    ``start`` counts seconds from the real IMU's first sample; the first sample is the next
    trigger sample at or after it (and after the ground truth's first row); ``duration``
    seconds of samples follow (to half a sample period), ending inside the ground truth.

    Raises:
        DataError: the window does not fit in the time both the IMU and the ground truth cover
            (the message says how much there is).
    """
    imu_t = np.asarray(real.imu.t_ns, np.int64)
    gt_t = np.asarray(real.ground_truth.t_ns, np.int64)
    period = int(round(1e9 / real.imu_calibration.rate_hz))
    lo, hi = max(int(imu_t[0]), int(gt_t[0])), min(int(imu_t[-1]), int(gt_t[-1]))
    if hi <= lo:
        raise DataError("the IMU and the ground truth do not overlap in time", where)
    cam0 = real.cameras.get("cam0")
    phase = None if cam0 is None else trigger_phase(imu_t, cam0.t_ns, ratio)
    phase_from = "imu" if phase is None else "cam0"

    i0 = int(np.searchsorted(imu_t, max(int(imu_t[0]) + int(round(start * 1e9)), lo)))
    if phase is None:
        phase = i0 % ratio
    i0 += (phase - i0) % ratio
    covered = (hi - int(imu_t[0])) * 1e-9
    if i0 >= len(imu_t) or imu_t[i0] > hi:
        raise DataError(f"start {start:g} s is past the end of the real recording (its IMU and "
                        f"ground truth cover {covered:.3f} s from the first IMU sample)", where)
    t0 = int(imu_t[i0])
    t1 = t0 + int(round(duration * 1e9))
    if t1 > hi + period // 2:
        raise DataError(f"start {start:g} s + duration {duration:g} s runs past the end of the "
                        f"real recording (its IMU and ground truth cover {covered:.3f} s from "
                        f"the first IMU sample; at most {(hi - t0) * 1e-9:.3f} s from this "
                        "start)", where)
    i1 = int(np.searchsorted(imu_t, min(t1 + period // 2, hi), side="right"))
    idx = np.arange(i0, i1)
    cam_t = imu_t[idx[(idx - phase) % ratio == 0]]
    gt = (gt_t >= t0 - GT_TOLERANCE_NS) & (gt_t <= int(imu_t[i1 - 1]) + GT_TOLERANCE_NS)
    return HybridSpan(slice(i0, i1), cam_t, gt, int(phase), phase_from, ratio)


def _imu_slice(imu: ImuData, span: slice) -> ImuData:
    return ImuData(t_ns=imu.t_ns[span], gyro=imu.gyro[span], accel=imu.accel[span])


def _gt_rows(gt: GroundTruth, keep: np.ndarray) -> GroundTruth:
    def take(a):
        return None if a is None else np.asarray(a)[keep]
    return GroundTruth(t_ns=gt.t_ns[keep], position=gt.position[keep],
                       quaternion=gt.quaternion[keep], velocity=take(gt.velocity),
                       bias_gyro=take(gt.bias_gyro), bias_accel=take(gt.bias_accel))


def read_real(real: str | Path) -> Sequence:
    """The real recording, checked for what a hybrid needs: IMU samples and their
    calibration with the body frame being the IMU frame, and a ground truth.

    Raises:
        DataError: one line naming the folder and what is missing.
    """
    path = Path(real)
    seq, _ = read_sequence(path)
    if seq.imu is None or len(seq.imu) < 2 or seq.imu_calibration is None:
        raise DataError(f"no IMU samples ({fmt.IMU_FOLDER}): a hybrid keeps the real IMU", path)
    if seq.ground_truth is None or len(seq.ground_truth) < 2:
        raise DataError(f"no ground truth ({fmt.GROUND_TRUTH_FOLDER}): a hybrid flies the real "
                        "trajectory", path)
    if not np.allclose(seq.imu_calibration.T_BS, np.eye(4), atol=1e-9):
        raise DataError(f"{fmt.IMU_FOLDER} T_BS is not the identity: a hybrid needs the body "
                        "frame (the ground truth's) to be the IMU frame", path)
    return seq


def simulate_hybrid(real: str | Path, out_dir: str | Path, config: SimConfig | None = None,
                    *, start: float | None = None, duration: float | None = None,
                    progress: bool = True, overwrite: bool = False) -> SimReport:
    """Write a hybrid recording: the real IMU and ground truth of ``real`` over a span, with
    the simulator's stereo frames (and depth, target labels) rendered along the real flight
    (see the module docstring).

    Args:
        real: the real recording (EuRoC ASL folder or bag) with IMU and ground truth.
        out_dir: the output folder; must not exist or be empty unless ``overwrite``.
        config: the simulator's settings (frames, camera, seed, ``imu_offset``; default
            :class:`SimConfig`). ``trajectory`` is ignored, ``imu_noise`` does not apply (the
            noise is real), nor do the simulated IMU's errors
            (:data:`~uavcal_jax.sim.config.IMU_ERRORS`: the real IMU has its own vibration,
            intrinsics and clock; at their defaults they are turned off, set to anything else
            they are refused, as is ``imu_rotation_deg``), and ``imu_rate_hz`` becomes the real
            IMU's rate.
        start: seconds after the real IMU's first sample (default ``config.start``).
        duration: seconds (default ``config.duration``).
        progress: a progress bar on stderr.
        overwrite: replace ``out_dir`` when it holds a previous simulation.

    Returns:
        The :class:`~uavcal_jax.sim.simulate.SimReport` (``resolved`` is
        ``sim_config.json``'s content).

    Raises:
        DataError: ``real`` unreadable, without IMU or ground truth, a span outside it, or an
            output folder in the way. ``ValueError``: an invalid configuration, or a camera
            rate that does not divide the IMU rate.
    """
    real = Path(real)
    config = SimConfig() if config is None else config
    seq = read_real(real)
    config = dataclasses.replace(
        config, trajectory=None, **{name: IDEAL_SENSORS[name] for name in IMU_ERRORS
                                    if getattr(config, name) == _DEFAULTS[name]},
        start=config.start if start is None else float(start),
        duration=config.duration if duration is None else float(duration),
        imu_rate_hz=float(seq.imu_calibration.rate_hz))
    config.validate()
    if config.imu_rotation_deg is not None:
        raise ValueError("imu_rotation_deg does not apply to a hybrid recording (the real "
                         "IMU is where it was mounted)")
    simulated_errors = [name for name in IMU_ERRORS
                        if getattr(config, name) not in (_DEFAULTS[name], IDEAL_SENSORS[name])]
    if simulated_errors:
        raise ValueError(f"{', '.join(simulated_errors)} do not apply to a hybrid recording (the "
                         "real IMU has its own vibration, intrinsics and clock)")
    ratio = config.imu_rate_hz / config.camera_rate_hz
    if abs(ratio - round(ratio)) > 1e-9:
        raise ValueError(f"camera_rate_hz {config.camera_rate_hz:g} must divide the real IMU's "
                         f"rate {config.imu_rate_hz:g} Hz (the cameras are triggered on IMU "
                         "samples)")
    span = hybrid_span(seq, config.start, config.duration, int(round(ratio)), real)
    out_dir = Path(out_dir)
    check_out_dir(out_dir, overwrite)
    report = write_recording_atomically(out_dir, lambda root: _hybrid_into(
        seq, real, span, config, root, progress))
    report.root = out_dir
    return report


def _hybrid_into(seq: Sequence, real: Path, span: HybridSpan, config: SimConfig, root: Path,
                 show_progress: bool) -> SimReport:
    t_begin = time.perf_counter()
    timings: dict[str, float] = {}
    seeds = stage_seeds(config.seed)
    imu = _imu_slice(seq.imu, span.imu)
    gt = _gt_rows(seq.ground_truth, span.gt)
    t0_ns, t1_ns = int(imu.t_ns[0]), int(imu.t_ns[-1])
    try:
        traj = fit_tum_trajectory(seq.ground_truth, start=t0_ns * 1e-9,
                                  duration=(t1_ns - t0_ns) * 1e-9, where=real)
    except ValueError as err:  # DataError included: name the real recording
        raise DataError(f"cannot fit a trajectory to the ground truth: {err}", real) from None
    timings["trajectory_imu"] = time.perf_counter() - t_begin

    real_cam = seq.cameras.get("cam0")
    real_in_span = 0 if real_cam is None else int(np.count_nonzero(
        (real_cam.t_ns >= t0_ns) & (real_cam.t_ns <= t1_ns)))
    flight: dict[str, Any] = {
        "source": "hybrid", "real": str(real.resolve()), "imu": "real", "ground_truth": "real",
        "real_first_t_ns": int(seq.imu.t_ns[0]), "start_s_after_first": float(config.start),
        "camera_trigger": {"every_imu_samples": span.ratio, "phase": span.phase,
                           "phase_from": span.phase_from,
                           "real_cam0_frames_in_span": real_in_span},
        "t_start_ns": t0_ns, "t_end_ns": t1_ns,
    }
    calibs = camera_calibrations(config)
    resolved: dict[str, Any] = {
        "uavcal_jax_version": __version__,
        "config": config.to_dict(),
        "seeds": seeds,
        "flight": flight,
        "imu_noise": None,  # the real sensor's: its densities are in imu_calibration
        "imu_calibration": calib_dict(seq.imu_calibration),
        "counts": {"imu": len(imu), "ground_truth": len(gt)},
    }

    t_write = time.perf_counter()
    comment = f"real IMU samples of {seq.name} (uavcal-jax hybrid recording)"
    if config.imu_offset is not None:
        comment += f" plus a constant offset (imu_offset in {SIM_CONFIG_FILE})"
    with EurocWriter(root, workers=config.png_workers,
                     body_comment=f"uavcal-jax hybrid: real IMU and ground truth of {seq.name}, "
                                  "simulated cameras") as writer:
        writer.write_imu(with_offset(imu, config.imu_offset), seq.imu_calibration,
                         comment=comment)
        writer.write_ground_truth(gt, comment=f"Real ground truth of {seq.name} (rows copied); "
                                              "the frames follow a trajectory fitted to it.")
        write_s = time.perf_counter() - t_write
        if config.frames:
            write_s += render_into_report(resolved, timings, config, traj, imu.t_ns, calibs,
                                          seeds, writer, show_progress, cam_t_ns=span.cam_t_ns)
        t_close = time.perf_counter()
    return finish_report(root, resolved, timings, writer, write_s, t_close, t_begin)
