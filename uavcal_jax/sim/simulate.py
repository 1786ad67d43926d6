"""The flight simulator's orchestration: trajectory -> IMU + ground truth -> rendered frames,
depth and target labels -> an EuRoC ASL folder.

One job, the order of the stages and what each hands the next; the stages themselves live in
their modules (trajectory fit, IMU synthesis, frames, writer). Its length is the recording's
contract spelled out below (time base, body frame, IMU errors, the resolved configuration).

:func:`simulate` writes ``out_dir/mav0`` (the layout of :mod:`uavcal_jax.data.euroc_format`)
and ``out_dir/sim_config.json`` (the resolved configuration: every default, the seeds of each
stage, the calibration written, the time range and the counts). The output is built in a
temporary sibling folder (``.<name>.partial-*``) and renamed at the end, so a folder named
``out_dir`` is always a complete recording. The configuration is a
:class:`~uavcal_jax.sim.config.SimConfig`; the camera stage is :mod:`uavcal_jax.sim.frames`.

Time. A trajectory file keeps its own clock: ``SimConfig.start`` counts seconds from the
file's first timestamp, and every timestamp written (IMU, ground truth, frames) is on the
file's clock, so a simulated and a real recording of the same flight line up. A procedural
flight starts at the trajectory's own ``t_start`` (0 s). Cameras are triggered on IMU samples
(as in EuRoC: every ``imu_rate_hz / camera_rate_hz``-th IMU timestamp) when the rates divide;
the scene (moving targets) is evaluated at seconds since the flight's first sample.

Trajectory files. The poses are fitted with smoothing matched to the noise measured on them
(:func:`uavcal_jax.sim.trajectory_fit.fit_trajectory_report`: irregular intervals,
near-duplicate stamps, gaps and position steps are handled); ``sim_config.json`` records the
fit's residual and the flight's peak specific force and angular rate
(``flight.trajectory_fit``). A flight beyond what a drone flies is simulated with a
:class:`~uavcal_jax.errors.FlightLimitWarning`; one no airframe could fly (a broken
file) is refused with a ``DataError`` (the limits are
:class:`~uavcal_jax.sim.trajectory_fit.FitConfig` fields).

Body frame. The body frame is the IMU frame. A trajectory file is EuRoC's IMU frame already
(``SimConfig.body_frame="euroc"``); a procedural flight, and a file with ``body_frame="flu"``
(a quadrotor frame: x forward, y left, z up), gets EuRoC's IMU mounting (:func:`mount_imu`:
IMU x up, z forward and 20 degrees down), so EuRoC's camera extrinsics look ahead and the IMU
reads gravity on x as EuRoC's does. ``SimConfig.camera_pitch_deg`` turns the stereo rig
(:func:`uavcal_jax.sim.mounting.pitched_rig`; the cameras' ``T_BS`` are the turned ones).

IMU offset. ``SimConfig.imu_offset`` makes a miscalibrated recording: the offset is added
(:func:`uavcal_jax.imu.offset.add_offset`) to the samples written to ``imu0/data.csv`` after
their noise and biases are drawn, so the noise streams are those of the same run without it and
the ground truth's bias columns stay the IMU's true biases; the offset itself is recorded in
``sim_config.json`` (``config.imu_offset``).

IMU errors. ``SimConfig.imu_vibration``, ``imu_scale``, ``imu_misalignment``,
``imu_g_sensitivity`` and ``imu_time_offset`` (:data:`~uavcal_jax.sim.config.IMU_ERRORS`; by
default :data:`~uavcal_jax.sim.config.EUROC_IMU_REALISM`'s EuRoC-like values, no clock
offset) make the IMU read rotor vibration, scale and axis errors, g-sensitivity and a clock
offset (:func:`uavcal_jax.sim.imu_synth.synthesize_imu`); the ground truth stays the motion,
its bias columns the biases plus what the scale, misalignment and g-sensitivity add
(:func:`intrinsic_error`: the IMU's systematic error at each sample), and the vibration
spectrum used is recorded in ``sim_config.json`` (``imu_vibration_spectrum``; a recorded
flight's standing one as ``imu_rest_vibration_spectrum``).

Frames. Both EuRoC cameras (cam0, cam1: intrinsics, radial-tangential distortion and
``T_BS`` of the real VI-sensor) are rendered; another resolution scales the intrinsics (same
field of view).

Determinism. Everything random derives from ``SimConfig.seed``: the same configuration gives
byte-identical files.

One module over 450 lines, one job: the orchestration above, from a configuration to a
written recording; each stage it calls (trajectory fit, IMU synthesis, rendering, writing)
is a module of its own.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial.transform import Rotation

from uavcal_jax import __version__
from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.data.euroc_rig import euroc_imu_mounting
from uavcal_jax.data.euroc_writer import EurocWriter
from uavcal_jax.data.sequence import GroundTruth, ImuCalibration, ImuData
from uavcal_jax.data.sim_config import SIM_CONFIG_FILE, write_sim_config
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.imu.offset import add_offset
from uavcal_jax.sim import imu_synth
from uavcal_jax.sim.config import (
    IMU_ERRORS,
    SimConfig,
    camera_calibrations,
    imu_rotation,
    stage_seeds,
)
from uavcal_jax.sim.flights import FlightConfig, procedural_flight
from uavcal_jax.sim.frames import render_frames
from uavcal_jax.sim.imu_vibration import EUROC_V101_REST_VIBRATION, EUROC_V101_VIBRATION
from uavcal_jax.sim.trajectory import Trajectory
from uavcal_jax.sim.trajectory_fit import FitConfig, check_flight_limits, fit_trajectory_report

__all__ = ["SimReport", "calib_dict", "check_out_dir", "finish_report", "imu_calibration",
           "imu_error_options", "imu_intrinsics", "intrinsic_error", "load_flight", "mount_imu",
           "render_into_report", "simulate", "simulate_report", "with_offset",
           "write_recording_atomically"]


@dataclass
class SimReport:
    """What :func:`simulate_report` did.

    Attributes:
        root: the output folder (holds ``mav0`` and ``sim_config.json``).
        resolved: the content of ``sim_config.json`` (:mod:`uavcal_jax.data.sim_config`).
        timings: wall seconds per stage: ``trajectory_imu``, ``compile`` (renderer, first
            call), ``render`` (waiting for JAX), ``write`` (waiting for the PNG encoders and
            writing tables), ``encode`` (PNG encoder thread time, overlapped with rendering),
            ``total``.
    """

    root: Path
    resolved: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Calibration and flight
# --------------------------------------------------------------------------------------------


def imu_calibration(config: SimConfig) -> ImuCalibration:
    """EuRoC's ADIS16448 noise model (the one :func:`simulate` draws from), identity ``T_BS``
    (the body frame is the IMU frame)."""
    return ImuCalibration(rate_hz=float(config.imu_rate_hz), T_BS=np.eye(4),
                          noise=EUROC_ADIS16448)


def load_flight(config: SimConfig, seeds: dict[str, int]
                ) -> tuple[Trajectory, np.ndarray, dict[str, Any]]:
    """The flight's :class:`~uavcal_jax.sim.trajectory.Trajectory`, the IMU (and ground-truth)
    timestamps, and a description of the flight.

    The timestamps are ``t0 + k * round(1e9 / imu_rate_hz)`` ns over ``duration``; for a
    trajectory file ``t0`` is the file's first timestamp plus ``start``, exactly in integer
    nanoseconds (so with EuRoC's 200 Hz ground truth and a ``start`` on its 5 ms grid, the IMU
    samples fall on the file's own timestamps).

    A trajectory file's fit is described under ``"trajectory_fit"``
    (:class:`~uavcal_jax.sim.trajectory_fit.FitReport`: residual, measured noise, peak
    specific force and angular rate over the window), and checked against a drone's limits
    (:func:`~uavcal_jax.sim.trajectory_fit.check_flight_limits`: a
    :class:`~uavcal_jax.errors.FlightLimitWarning` beyond them).

    Raises:
        DataError: the trajectory file is unreadable, ``start``/``duration`` fall outside
            its time range, or its fitted flight is beyond any airframe (a broken file); the
            message names the file.
    """
    period_ns = int(round(1e9 / config.imu_rate_hz))
    n = int(np.floor(config.duration * config.imu_rate_hz + 1e-9)) + 1
    if config.trajectory is None:
        # Procedural flights have a quadrotor body frame (z up); the IMU is mounted as on
        # EuRoC's MAV, so EuRoC's camera extrinsics look forward.
        airframe = FlightConfig(rotor_drag=config.rotor_drag,
                                thrust_tilt_deg=config.thrust_tilt_deg or (0.0, 0.0))
        traj = mount_imu(procedural_flight(seeds["flight"], config.duration, airframe),
                         euroc_imu_mounting())
        t0_ns = int(np.ceil(traj.t_start * 1e9 - 1e-3))
        info: dict[str, Any] = {"source": "procedural", "seed": seeds["flight"]}
    else:
        path = Path(config.trajectory)
        gt = read_tum(path)
        first_ns, last_ns = int(gt.t_ns[0]), int(gt.t_ns[-1])
        span = (last_ns - first_ns) * 1e-9
        if config.start >= span:
            raise DataError(f"--start {config.start:g} s is past the end of the trajectory "
                            f"(it spans {span:.3f} s from its first timestamp)", path)
        t0_ns = first_ns + int(round(config.start * 1e9))
        if t0_ns + (n - 1) * period_ns > last_ns:
            raise DataError(f"--start {config.start:g} s + --duration {config.duration:g} s "
                            f"runs past the end of the trajectory (it spans {span:.3f} s; at "
                            f"most {span - config.start:.3f} s from this start)", path)
        fit_config = FitConfig()
        try:
            traj, fit = fit_trajectory_report(gt, start=t0_ns * 1e-9, duration=config.duration,
                                              config=fit_config, where=path)
        except ValueError as err:
            raise DataError(f"cannot fit a trajectory: {err}", path) from None
        check_flight_limits(fit, fit_config, path)
        if config.body_frame == "flu":
            # the file's body is a quadrotor frame (x forward, z up): EuRoC's IMU is mounted
            # on it as on the procedural flights, so the rig looks forward and the IMU reads
            # gravity on x (a constant rotation: the fit's peak force and rate are unchanged)
            traj = mount_imu(traj, euroc_imu_mounting())
        info = {"source": str(path.resolve()), "file_first_t_ns": first_ns,
                "file_last_t_ns": last_ns, "start_s_after_first": float(config.start),
                "body_frame": config.body_frame, "trajectory_fit": fit.to_dict()}
    if config.imu_rotation_deg is not None:
        # the IMU turned on the airframe: the body frame is the turned IMU's
        traj = mount_imu(traj, imu_rotation(config))
    t_ns = t0_ns + period_ns * np.arange(n, dtype=np.int64)
    return traj, t_ns, info


def imu_error_options(config: SimConfig, recorded: bool | None = None) -> dict:
    """``config``'s IMU errors beyond its noise (:data:`~uavcal_jax.sim.config.IMU_ERRORS`) as
    :func:`~uavcal_jax.sim.imu_synth.synthesize_imu`'s keyword arguments.

    ``recorded``: whether the trajectory is a recorded flight (default: ``config.trajectory``
    is a file). Only there does ``imu_rest_vibration`` apply: a recorded flight's still seconds
    are the MAV standing with its rotors idling, while a planned flight (procedural, straight)
    hovers exactly still in flight, rotors at hover speed.
    """
    recorded = config.trajectory is not None if recorded is None else recorded
    vibrates = bool(config.imu_vibration)
    rests = vibrates and recorded and config.imu_rest_vibration
    return {"vibration": EUROC_V101_VIBRATION if vibrates else None,
            "rest_vibration": EUROC_V101_REST_VIBRATION if rests else None,
            "vibration_scale": config.imu_vibration, "intrinsics": imu_intrinsics(config),
            "time_offset": config.imu_time_offset}


def intrinsic_error(traj, t_ns: np.ndarray, config: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(gyro (N, 3) rad/s, accel (N, 3) m/s^2)``: what ``config``'s scale, misalignment and
    g-sensitivity add to the exact measurements of the motion ``traj`` at the IMU's stamps
    ``t_ns`` (zeros for an ideal sensor). The vibration, zero-mean, is left out: like the white
    noise it is no error a constant or a slowly varying bias can correct.

    The simulator writes it into the ground truth's bias columns with the sensor's bias: they
    hold the IMU's systematic error at each sample, so their mean over a span is the constant
    that best corrects it (:func:`uavcal_jax.data.true_offset.sensor_bias`), as the bias
    columns of a real EuRoC ground truth (an estimator's) absorb the same errors.
    """
    intrinsics = imu_intrinsics(config)
    n = len(t_ns)
    if intrinsics is None:
        return np.zeros((n, 3)), np.zeros((n, 3))
    exact = imu_synth.synthesize_imu(traj, config.imu_rate_hz, None, t_ns=t_ns,
                                     time_offset=config.imu_time_offset).imu
    gyro, accel = intrinsics.apply(exact.gyro, exact.accel)
    return gyro - exact.gyro, accel - exact.accel


def imu_intrinsics(config: SimConfig) -> imu_synth.ImuIntrinsics | None:
    """The configuration's scale, misalignment and g-sensitivity (``None`` when all three are
    absent: an ideal sensor, and the samples stay those of a run without the options)."""
    if (config.imu_scale, config.imu_misalignment, config.imu_g_sensitivity) == (None,) * 3:
        return None
    return imu_synth.ImuIntrinsics.from_errors(config.imu_scale, config.imu_misalignment,
                                               config.imu_g_sensitivity)


def with_offset(imu: ImuData, offset: tuple[float, ...] | None) -> ImuData:
    """``imu`` as read by a sensor with the constant ``offset`` (6,) (gyro rad/s, accel
    m/s^2; ``None``: unchanged), in float64."""
    if offset is None:
        return imu
    # 64-bit JAX: the default 32-bit arrays would round the written samples to ~1e-6 m/s^2
    with jax.enable_x64(True):
        gyro, accel = add_offset(imu.gyro, imu.accel, np.asarray(offset, dtype=np.float64))
        gyro, accel = np.asarray(gyro, np.float64), np.asarray(accel, np.float64)
    return dataclasses.replace(imu, gyro=gyro, accel=accel)


def mount_imu(traj: Trajectory, R_QB: np.ndarray) -> Trajectory:
    """The same motion with the body frame rotated by the constant ``R_QB`` (new body axes in
    the old body frame): ``R_WB' = R_WB R_QB``.

    The quaternion spline's coefficients ``c_i`` are right-multiplied by ``q(R_QB)``: linear in
    the coefficients, so the spline, its derivatives and the body rate stay exact. The
    coefficients are not unit quaternions, so each is composed as ``|c_i| (c_i / |c_i|) q``.
    """
    spline = traj.quaternion_spline
    coef = np.asarray(spline.c, dtype=np.float64)
    norm = np.linalg.norm(coef, axis=1, keepdims=True)
    # scipy keeps the sign of a composed quaternion (no canonical form), as the spline needs
    turned = Rotation.from_quat(coef[:, [1, 2, 3, 0]]) * Rotation.from_matrix(R_QB)
    coef = norm * turned.as_quat()[:, [3, 0, 1, 2]]
    return dataclasses.replace(
        traj, quaternion_spline=BSpline(spline.t, coef, spline.k, extrapolate=spline.extrapolate))


# --------------------------------------------------------------------------------------------
# Output folder
# --------------------------------------------------------------------------------------------


def _looks_replaceable(folder: Path) -> bool:
    """Only an empty folder or a previous simulation may be replaced by ``overwrite``."""
    entries = {p.name for p in folder.iterdir()}
    return not entries or SIM_CONFIG_FILE in entries or entries <= {fmt.MAV0}


def check_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Refuse (:class:`DataError`) an ``out_dir`` that holds anything but an empty folder, or,
    with ``overwrite``, a previous simulation."""
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise DataError("output path exists and is not a folder", out_dir)
    if not any(out_dir.iterdir()):
        return
    if not overwrite:
        raise DataError("output folder exists and is not empty (use --overwrite to replace "
                        "it)", out_dir)
    if not _looks_replaceable(out_dir):
        raise DataError(f"output folder is not a previous simulation (no {SIM_CONFIG_FILE}); "
                        "refusing to replace it", out_dir)


def simulate(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
             overwrite: bool = False) -> Path:
    """Simulate a flight and write it as an EuRoC ASL folder ``out_dir/mav0``.

    Args:
        config: the simulation.
        out_dir: the output folder; must not exist or be empty unless ``overwrite``.
        progress: show a progress bar on stderr.
        overwrite: replace ``out_dir`` when it holds a previous simulation.

    Returns:
        ``out_dir`` (pass it to :func:`uavcal_jax.data.read_euroc`).

    Raises:
        DataError: unreadable trajectory file, start/duration outside it, or an output folder
            that is in the way. ``ValueError`` for an invalid configuration.
    """
    return simulate_report(config, out_dir, progress, overwrite=overwrite).root


def simulate_report(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
                    overwrite: bool = False) -> SimReport:
    """:func:`simulate`, returning the resolved configuration and per-stage timings too."""
    config.validate()
    out_dir = Path(out_dir)
    check_out_dir(out_dir, overwrite)
    return write_recording_atomically(out_dir, lambda root: _simulate_into(config, root,
                                                                             progress))


def write_recording_atomically(out_dir: Path, build: Callable[[Path], SimReport]) -> SimReport:
    """``build`` a recording into a temporary sibling folder, write its ``sim_config.json``
    last and rename the folder to ``out_dir`` (replacing a previous simulation there): an
    interrupted run leaves no half-written recording under ``out_dir``. Returns the report
    with ``root`` set to ``out_dir``."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        report = build(tmp)
        write_sim_config(tmp, report.resolved)
        if out_dir.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
            os.replace(out_dir, trash / "old")
            os.replace(tmp, out_dir)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    report.root = out_dir
    return report


def _simulate_into(config: SimConfig, root: Path, show_progress: bool) -> SimReport:
    t_begin = time.perf_counter()
    timings: dict[str, float] = {}
    seeds = stage_seeds(config.seed)

    # 1. Flight, IMU, ground truth.
    traj, imu_t_ns, flight = load_flight(config, seeds)
    imu_calib = imu_calibration(config)
    noise = imu_calib.noise if config.imu_noise else None
    turn_on = imu_synth.TurnOnBias()
    errors = imu_error_options(config)
    vibration = errors["vibration"]
    synth = imu_synth.synthesize_imu(
        traj, rate_hz=config.imu_rate_hz, noise=noise, seed=seeds["imu"], t_ns=imu_t_ns,
        turn_on=turn_on, **errors)
    imu = synth.imu
    # the ground truth keeps the true biases, with what the scale, misalignment and
    # g-sensitivity add to the motion: the offset is an extra error of the written IMU
    extra_gyro, extra_accel = intrinsic_error(traj, imu.t_ns, config)
    gt: GroundTruth = imu_synth.ground_truth_from_trajectory(
        traj, imu.t_ns, bias_gyro=synth.bias_gyro + extra_gyro,
        bias_accel=synth.bias_accel + extra_accel)
    timings["trajectory_imu"] = time.perf_counter() - t_begin

    calibs = camera_calibrations(config)
    resolved: dict[str, Any] = {
        "uavcal_jax_version": __version__,
        "config": config.to_dict(),
        "seeds": seeds,
        "flight": {**flight, "t_start_ns": int(imu.t_ns[0]), "t_end_ns": int(imu.t_ns[-1])},
        "imu_noise": ({**dataclasses.asdict(noise), "turn_on_bias": dataclasses.asdict(turn_on)}
                      if noise is not None else None),
        "imu_calibration": calib_dict(imu_calib),
        "counts": {"imu": len(imu), "ground_truth": len(gt)},
    }
    if vibration is not None:
        resolved["imu_vibration_spectrum"] = vibration.to_dict()
    if errors["rest_vibration"] is not None:
        resolved["imu_rest_vibration_spectrum"] = errors["rest_vibration"].to_dict()

    t_write = time.perf_counter()
    with EurocWriter(root, workers=config.png_workers) as writer:
        writer.write_imu(with_offset(imu, config.imu_offset), imu_calib,
                         comment=_imu_comment(config))
        writer.write_ground_truth(gt)
        write_s = time.perf_counter() - t_write

        if config.frames:
            write_s += render_into_report(resolved, timings, config, traj, imu.t_ns, calibs,
                                          seeds, writer, show_progress)
        t_close = time.perf_counter()
    return finish_report(root, resolved, timings, writer, write_s, t_close, t_begin)


def render_into_report(resolved: dict, timings: dict, config: SimConfig, traj,
                       imu_t_ns: np.ndarray, calibs: dict, seeds: dict, writer: EurocWriter,
                       show_progress: bool, cam_t_ns: np.ndarray | None = None) -> float:
    """Render the frames (:func:`~uavcal_jax.sim.frames.render_frames`) into ``writer``,
    recording the cameras, scene and counts in ``resolved`` and the stage times in
    ``timings`` (both updated in place); returns the seconds spent waiting on the writer."""
    frame_info, frame_timings = render_frames(config, traj, imu_t_ns, calibs, seeds["scene"],
                                              writer, show_progress,
                                              camera_seed=seeds["camera"], cam_t_ns=cam_t_ns)
    resolved["cameras"] = {k: calib_dict(c) for k, c in calibs.items()}
    resolved["camera_model"] = frame_info["camera_model"]
    resolved["scene"] = frame_info["scene"]
    resolved["counts"].update(frame_info["counts"])
    timings.update(frame_timings)
    return timings.pop("write_wait")


def finish_report(root: Path, resolved: dict, timings: dict, writer: EurocWriter,
                  write_s: float, t_close: float, t_begin: float) -> SimReport:
    """The :class:`SimReport` once the writer has closed (at ``t_close``, ``perf_counter``
    seconds; the simulation began at ``t_begin``): the write, encode and total seconds added
    to ``timings``."""
    timings["write"] = write_s + time.perf_counter() - t_close
    timings["encode"] = writer.encode_seconds
    timings["total"] = time.perf_counter() - t_begin
    return SimReport(root=root, resolved=resolved, timings=timings)


def _imu_comment(config: SimConfig) -> str:
    """``imu0/sensor.yaml``'s comment: how the samples were made."""
    text = ("uavcal-jax simulated IMU (EuRoC ADIS16448 noise model)" if config.imu_noise
            else "uavcal-jax simulated IMU (exact, no noise)")
    if config.imu_offset is not None:
        text += f" plus a constant offset (imu_offset in {SIM_CONFIG_FILE})"
    extras = [name for name in IMU_ERRORS if getattr(config, name)]
    if extras:
        text += f" with {', '.join(extras)} (in {SIM_CONFIG_FILE})"
    return text


def calib_dict(calib) -> dict[str, Any]:
    """A calibration record as JSON-ready values (for ``sim_config.json``)."""
    d = dataclasses.asdict(calib)
    return {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray | tuple) else v)
            for k, v in d.items()}
