"""The flight simulator's orchestration: trajectory -> IMU + ground truth -> rendered frames,
depth and target labels -> an EuRoC ASL folder.

:func:`simulate` writes ``out_dir/mav0`` (see :mod:`uavcal_jax.sim.writer` for the layout) and
``out_dir/sim_config.json`` (the resolved configuration: every default, the seeds of each
stage, the calibration written, the time range and the counts). The output is built in a
temporary sibling folder (``.<name>.partial-*``) and renamed at the end, so a folder named
``out_dir`` is always a complete recording.

Time. A trajectory file keeps its own clock: ``SimConfig.start`` counts seconds from the
file's first timestamp, and every timestamp written (IMU, ground truth, frames) is on the
file's clock, so a simulated and a real recording of the same flight line up. A procedural
flight starts at the trajectory's own ``t_start`` (0 s). Cameras are triggered on IMU samples (as in
EuRoC: every ``imu_rate_hz / camera_rate_hz``-th IMU timestamp) when the rates divide; the
scene (moving targets) is evaluated at seconds since the flight's first sample.

Body frame. The body frame is the IMU frame. A trajectory file is EuRoC's IMU frame already; a
procedural flight (a quadrotor frame, z up) gets EuRoC's IMU mounting (:func:`mount_imu`: IMU
x up, z forward and 20 degrees down), so EuRoC's camera extrinsics look ahead and the IMU
reads gravity on x as EuRoC's does.

Frames. Both EuRoC cameras (cam0, cam1: intrinsics, radial-tangential distortion and
``T_BS`` of the real VI-sensor) are rendered at ``T_WC = T_WB(t) @ T_BS``; another resolution
scales the intrinsics (same field of view). Depth ``depthN`` is cam N's z-depth in uint16
millimetres (0 = no depth), with cam N's calibration. Target labels (``target0``) list, for each
frame and camera, every target with visible pixels: the tight box around those pixels, their
count, and the target's 3D world position.

Speed. Frames are rendered in fixed-size batches by one jitted function (compiled once; the
last batch is padded), PNG encoding runs on a thread pool while JAX renders the next batch.

Determinism. Everything random derives from ``SimConfig.seed``: the same configuration gives
byte-identical files.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial.transform import Rotation

from uavcal_jax import __version__
from uavcal_jax.data.sequence import CameraCalibration, GroundTruth, ImuCalibration
from uavcal_jax.data.targets import TargetLabels
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError
from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim import imu_synth, render, scene, trajectory
from uavcal_jax.sim.writer import EurocWriter, depth_to_millimetres

#: Simulated camera names; cam N uses EuRoC's cam N calibration.
CAMERAS = ("cam0", "cam1")
#: EuRoC's cameras look this far below the horizon in level flight (the median over EuRoC's
#: ground truth of the IMU z axis' elevation: -20.2 deg V1_01, -19.3 MH_01, -19.2 V2_01).
EUROC_CAMERA_PITCH_DEG = 20.0


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated recording.

    Attributes:
        trajectory: TUM trajectory file to fly (``t tx ty tz qx qy qz qw``, t in seconds), or
            ``None`` for a procedural flight (hover, turns, climbs, straight legs) from ``seed``.
        start: seconds after the trajectory file's first timestamp where the recording starts
            (ignored for procedural flights). Output timestamps stay on the file's clock.
        duration: seconds of flight to record.
        resolution: ``(width, height)`` of the frames; other than EuRoC's 752x480, the EuRoC
            intrinsics are scaled to keep the field of view.
        color: ``"gray"`` (8-bit single channel, like EuRoC) or ``"rgb"``.
        seed: seeds the flight, the IMU noise and biases, and the scene.
        imu_noise: add EuRoC's ADIS16448 noise, bias random walk and turn-on biases; when false
            the IMU is exact (biases zero). ``imu0/sensor.yaml`` states EuRoC's noise model in
            both cases.
        frames: render and write cam0/cam1 (and depth, targets); false writes only the IMU and
            the ground truth.
        depth: write depth0/depth1 with the frames.
        targets: write target0 labels with the frames.
        camera_rate_hz: frame rate (EuRoC: 20 Hz).
        imu_rate_hz: IMU and ground-truth rate (EuRoC: 200 Hz).
        batch_size: frames rendered per jitted call (speed/memory only, not the output).
        png_workers: threads encoding PNGs (speed only).
    """

    trajectory: str | None = None
    start: float = 0.0
    duration: float = 10.0
    resolution: tuple[int, int] = camera_model.EUROC_RESOLUTION
    color: str = "gray"
    seed: int = 0
    imu_noise: bool = True
    frames: bool = True
    depth: bool = True
    targets: bool = True
    camera_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    batch_size: int = 8
    png_workers: int = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
        for name in ("start", "duration", "camera_rate_hz", "imu_rate_hz"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.trajectory is not None:
            object.__setattr__(self, "trajectory", os.fspath(self.trajectory))

    def validate(self) -> None:
        """Raise ``ValueError`` for values out of range (the file is checked by simulate)."""
        if self.color not in ("gray", "rgb"):
            raise ValueError(f"color must be 'gray' or 'rgb', got {self.color!r}")
        if not (np.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"duration must be positive, got {self.duration}")
        if not (np.isfinite(self.start) and self.start >= 0):
            raise ValueError(f"start must be >= 0 seconds, got {self.start}")
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise ValueError(f"resolution must be (width, height) >= 8 px, got {self.resolution}")
        for name in ("camera_rate_hz", "imu_rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.camera_rate_hz > self.imu_rate_hz:
            raise ValueError("camera_rate_hz must not exceed imu_rate_hz")
        if self.batch_size < 1 or self.png_workers < 1:
            raise ValueError("batch_size and png_workers must be >= 1")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["resolution"] = list(self.resolution)
        return d


@dataclass
class SimReport:
    """What :func:`simulate_report` did.

    Attributes:
        root: the output folder (holds ``mav0`` and ``sim_config.json``).
        resolved: the content of ``sim_config.json``.
        timings: wall seconds per stage: ``trajectory_imu``, ``compile`` (renderer, first
            call), ``render`` (waiting for JAX), ``write`` (waiting for the PNG encoders and
            writing tables), ``encode`` (PNG encoder thread time, overlapped with rendering),
            ``total``.
    """

    root: Path
    resolved: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------


def scale_calibration(calib: CameraCalibration, resolution: tuple[int, int]) -> CameraCalibration:
    """The same lens on an image of ``resolution = (width, height)`` (field of view kept).

    Pixel centres map as ``u' = sx (u + 0.5) - 0.5`` with ``sx = width' / width`` (and ``sy``
    likewise), the convention of :meth:`PinholeRadtan.scaled`; distortion is unchanged (it acts
    on normalised coordinates).
    """
    w0, h0 = calib.resolution
    w, h = (int(v) for v in resolution)
    if (w, h) == (w0, h0):
        return calib
    sx, sy = w / w0, h / h0
    fu, fv, cu, cv = np.asarray(calib.intrinsics, dtype=np.float64)
    intr = np.array([fu * sx, fv * sy, (cu + 0.5) * sx - 0.5, (cv + 0.5) * sy - 0.5])
    return dataclasses.replace(calib, intrinsics=intr, resolution=(w, h))


def camera_calibrations(config: SimConfig) -> dict[str, CameraCalibration]:
    """EuRoC cam0/cam1 at the configured resolution and frame rate."""
    out = {}
    for i, name in enumerate(CAMERAS):
        calib = scale_calibration(camera_model.euroc_calibration(i), config.resolution)
        out[name] = dataclasses.replace(calib, rate_hz=float(config.camera_rate_hz))
    return out


def imu_calibration(config: SimConfig) -> ImuCalibration:
    """EuRoC's ADIS16448 noise model (the defaults of :class:`imu_synth.ImuNoise`), identity
    ``T_BS`` (the body frame is the IMU frame)."""
    noise = imu_synth.ImuNoise()
    return ImuCalibration(
        rate_hz=float(config.imu_rate_hz),
        T_BS=np.eye(4),
        gyroscope_noise_density=float(noise.gyro_noise_density),
        gyroscope_random_walk=float(noise.gyro_random_walk),
        accelerometer_noise_density=float(noise.accel_noise_density),
        accelerometer_random_walk=float(noise.accel_random_walk),
    )


def stage_seeds(seed: int) -> dict[str, int]:
    """Independent seeds for the flight, the IMU noise and the scene, derived from ``seed``."""
    state = np.random.SeedSequence(int(seed)).generate_state(3, dtype=np.uint32)
    return {name: int(s) & 0x7FFFFFFF for name, s in zip(("flight", "imu", "scene"), state,
                                                         strict=True)}


# --------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------


def load_flight(config: SimConfig, seeds: dict[str, int]
                ) -> tuple[Any, np.ndarray, dict[str, Any]]:
    """The flight's :class:`~uavcal_jax.sim.trajectory.Trajectory`, the IMU (and ground-truth)
    timestamps, and a description of the flight.

    The timestamps are ``t0 + k * round(1e9 / imu_rate_hz)`` ns over ``duration``; for a
    trajectory file ``t0`` is the file's first timestamp plus ``start``, exactly in integer
    nanoseconds (so with EuRoC's 200 Hz ground truth and a ``start`` on its 5 ms grid, the IMU
    samples fall on the file's own timestamps).

    Raises:
        DataError: the trajectory file is unreadable, or ``start``/``duration`` fall outside
            its time range (the message names the file).
    """
    period_ns = int(round(1e9 / config.imu_rate_hz))
    n = int(np.floor(config.duration * config.imu_rate_hz + 1e-9)) + 1
    if config.trajectory is None:
        # Procedural flights have a quadrotor body frame (z up); the IMU is mounted as on
        # EuRoC's MAV, so EuRoC's camera extrinsics look forward.
        traj = mount_imu(trajectory.procedural_flight(seeds["flight"], config.duration),
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
        try:
            traj = trajectory.fit_tum_trajectory(gt, start=t0_ns * 1e-9,
                                                 duration=config.duration)
        except ValueError as err:
            raise DataError(f"cannot fit a trajectory: {err}", path) from None
        info = {"source": str(path.resolve()), "file_first_t_ns": first_ns,
                "file_last_t_ns": last_ns, "start_s_after_first": float(config.start)}
    t_ns = t0_ns + period_ns * np.arange(n, dtype=np.int64)
    return traj, t_ns, info


def euroc_imu_mounting(pitch_deg: float = EUROC_CAMERA_PITCH_DEG) -> np.ndarray:
    """(3, 3) ``R_QB``: EuRoC's IMU (body) axes in a quadrotor frame (x forward, y left, z up).

    EuRoC's VI-sensor has its IMU x axis up and z axis (where the cameras look) forward,
    pitched ``pitch_deg`` below the horizon; y points right.
    """
    th = np.radians(pitch_deg)
    s, c = np.sin(th), np.cos(th)
    return np.array([[s, 0.0, c], [0.0, -1.0, 0.0], [c, 0.0, -s]])


def mount_imu(traj, R_QB: np.ndarray):
    """The same motion with the body frame rotated by the constant ``R_QB`` (new body axes in
    the old body frame): ``R_WB' = R_WB R_QB``.

    The quaternion spline's coefficients are right-multiplied by ``q(R_QB)`` (linear in the
    coefficients, so the spline, its derivatives and the body rate stay exact).
    """
    x, y, z, w = Rotation.from_matrix(R_QB).as_quat()
    spline = traj.quaternion_spline
    coef = trajectory.quat_multiply(np.asarray(spline.c), np.array([w, x, y, z]))
    return dataclasses.replace(
        traj, quaternion_spline=BSpline(spline.t, coef, spline.k, extrapolate=spline.extrapolate))


def frame_times(imu_t_ns: np.ndarray, config: SimConfig) -> np.ndarray:
    """Camera timestamps (int64 ns): every k-th IMU timestamp when the rates divide (EuRoC's
    cameras are triggered with the IMU), else a ``1/camera_rate_hz`` grid from the first one."""
    ratio = config.imu_rate_hz / config.camera_rate_hz
    if abs(ratio - round(ratio)) < 1e-9:
        return np.asarray(imu_t_ns[:: int(round(ratio))], dtype=np.int64)
    t0, t1 = int(imu_t_ns[0]), int(imu_t_ns[-1])
    n = int(np.floor((t1 - t0) * 1e-9 * config.camera_rate_hz + 1e-9)) + 1
    return t0 + np.round(np.arange(n) * (1e9 / config.camera_rate_hz)).astype(np.int64)


def body_poses(traj, t_ns: np.ndarray) -> np.ndarray:
    """(N, 4, 4) float64 ``T_WB`` at int64 nanosecond times."""
    state = traj.state_ns(t_ns)
    T = np.zeros((t_ns.shape[0], 4, 4))
    T[:, :3, :3] = state.rotation
    T[:, :3, 3] = state.position
    T[:, 3, 3] = 1.0
    return T


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def make_frame_renderer(color: str, n_targets: int):
    """A jitted ``fn(scene, bundle0, bundle1, T_WC0 (B,4,4), T_WC1 (B,4,4), t (B,))`` returning
    per camera ``(image uint8 (B,H,W[,3]), depth uint16 mm (B,H,W), boxes (B,n,4),
    visible (B,n))``.

    ``bundleN`` is :func:`uavcal_jax.sim.render.ray_bundle` of camera N (an argument, not a
    baked-in constant). Frames are rendered by :func:`~uavcal_jax.sim.render.render_batch`;
    quantisation happens on the device, so only uint8 / uint16 images are transferred. Cached:
    simulations in one process share the compiled function."""

    def one_camera(scn, bundle, T_WC, t):
        out = render.render_batch(scn, None, T_WC, t, color=color, rays=bundle)
        img8 = jnp.clip(jnp.round(out.image * 255.0), 0, 255).astype(jnp.uint8)
        depth_mm = depth_to_millimetres(out.depth, jnp)
        boxes, visible = render.target_boxes(out.object_id, n_targets)
        return img8, depth_mm, boxes, visible

    def batch(scn, bundle0, bundle1, T0, T1, t):
        return one_camera(scn, bundle0, T0, t), one_camera(scn, bundle1, T1, t)

    return jax.jit(batch)


def _target_info(scn, t_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Class ids (n,), world positions (N, n, 3) at the frame times, and class names."""
    poses = np.asarray(jax.vmap(lambda t: scene.target_poses(scn, t))(jnp.asarray(t_rel)))
    class_id = np.asarray(scn.targets.class_id, dtype=np.int64).reshape(-1)
    return class_id, poses[..., :3, 3].astype(np.float64), scene.target_class_names(scn)


# --------------------------------------------------------------------------------------------
# Output folder
# --------------------------------------------------------------------------------------------


def _looks_replaceable(folder: Path) -> bool:
    """Only an empty folder or a previous simulation may be replaced by ``overwrite``."""
    entries = {p.name for p in folder.iterdir()}
    return not entries or "sim_config.json" in entries or entries <= {"mav0"}


def _check_out_dir(out_dir: Path, overwrite: bool) -> None:
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
        raise DataError("output folder is not a previous simulation (no sim_config.json); "
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
    _check_out_dir(out_dir, overwrite)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        report = _simulate_into(config, tmp, progress)
        (tmp / "sim_config.json").write_text(json.dumps(report.resolved, indent=2) + "\n")
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
    noise = imu_synth.ImuNoise() if config.imu_noise else None
    synth = imu_synth.synthesize_imu(traj, rate_hz=config.imu_rate_hz, noise=noise,
                                     seed=seeds["imu"], t_ns=imu_t_ns)
    imu = synth.imu
    gt: GroundTruth = imu_synth.ground_truth_from_trajectory(
        traj, imu.t_ns, bias_gyro=synth.bias_gyro, bias_accel=synth.bias_accel)
    timings["trajectory_imu"] = time.perf_counter() - t_begin

    calibs = camera_calibrations(config)
    imu_calib = imu_calibration(config)
    resolved: dict[str, Any] = {
        "uavcal_jax_version": __version__,
        "config": config.to_dict(),
        "seeds": seeds,
        "flight": {**flight, "t_start_ns": int(imu.t_ns[0]), "t_end_ns": int(imu.t_ns[-1])},
        "imu_noise": dataclasses.asdict(noise) if noise is not None else None,
        "imu_calibration": _calib_dict(imu_calib),
        "counts": {"imu": len(imu), "ground_truth": len(gt)},
    }

    t_write = time.perf_counter()
    with EurocWriter(root, workers=config.png_workers) as writer:
        writer.write_imu(imu, imu_calib, comment="uavcal-jax simulated IMU (EuRoC ADIS16448 "
                         "noise model)" if config.imu_noise else "uavcal-jax simulated IMU "
                         "(exact, no noise)")
        writer.write_ground_truth(gt)
        write_s = time.perf_counter() - t_write

        if config.frames:
            frame_info, frame_timings = _render_frames(config, traj, imu.t_ns, calibs,
                                                       seeds["scene"], writer, show_progress)
            resolved["cameras"] = {k: _calib_dict(c) for k, c in calibs.items()}
            resolved["scene"] = frame_info["scene"]
            resolved["counts"].update(frame_info["counts"])
            timings.update(frame_timings)
            write_s += timings.pop("write_wait")
        t_close = time.perf_counter()
    timings["write"] = write_s + time.perf_counter() - t_close
    timings["encode"] = writer.encode_seconds
    timings["total"] = time.perf_counter() - t_begin
    return SimReport(root=root, resolved=resolved, timings=timings)


def _render_frames(config: SimConfig, traj, imu_t_ns: np.ndarray,
                   calibs: dict[str, CameraCalibration], scene_seed: int, writer: EurocWriter,
                   show_progress: bool) -> tuple[dict[str, Any], dict[str, float]]:
    """Render both cameras at the frame times and queue frames, depth and labels to
    ``writer``. Returns the scene/counts description and the stage timings (``compile``,
    ``render``, ``write_wait``)."""

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    cam_t_ns = frame_times(imu_t_ns, config)
    n = cam_t_ns.shape[0]
    t_rel = (cam_t_ns - int(imu_t_ns[0])) * 1e-9  # scene clock: seconds since the first sample
    T_WB = body_poses(traj, cam_t_ns)
    T_WC = {name: T_WB @ calibs[name].T_BS for name in CAMERAS}

    lo, hi = traj.bounds()
    path_t = traj.times(10.0)
    path = traj.position(path_t)  # obstacles and targets keep clear of the path
    optical_axis = traj.rotation_matrix(path_t) @ calibs[CAMERAS[0]].T_BS[:3, 2]
    scn = scene.make_scene(lo, hi, scene_seed, path_points=path, view_directions=optical_axis)
    class_id, positions, class_names = _target_info(scn, t_rel)
    n_targets = int(class_id.shape[0])
    bundles = [jax.tree_util.tree_map(jnp.asarray, render.ray_bundle(
        camera_model.from_calibration(calibs[name]))) for name in CAMERAS]
    dtype = jnp.float32  # the renderer works in float32

    for name in CAMERAS:
        writer.add_image_stream(name, calibs[name], comment=f"uavcal-jax simulated {name} "
                                f"(EuRoC VI-Sensor {name} calibration)")
    if config.depth:
        for i, name in enumerate(CAMERAS):
            writer.add_image_stream(f"depth{i}", calibs[name], depth=True,
                                    comment=f"uavcal-jax simulated z-depth of {name}")

    B = min(config.batch_size, n)
    n_batches = -(-n // B)

    def batch_args(k):
        idx = np.minimum(np.arange(k * B, (k + 1) * B), n - 1)  # pad with the last frame
        return (jnp.asarray(T_WC["cam0"][idx], dtype), jnp.asarray(T_WC["cam1"][idx], dtype),
                jnp.asarray(t_rel[idx], dtype))

    fn = make_frame_renderer(config.color, n_targets)
    compiled = fn.lower(scn, bundles[0], bundles[1], *batch_args(0)).compile()
    timings["compile"] = time.perf_counter() - t0

    rows: list[tuple] = []
    render_wait = write_wait = 0.0
    bar = progress_bar(total=n, desc="simulate", unit="frame", enabled=show_progress)
    try:
        pending = compiled(scn, bundles[0], bundles[1], *batch_args(0))
        for k in range(n_batches):
            nxt = compiled(scn, bundles[0], bundles[1], *batch_args(k + 1)) if k + 1 < n_batches \
                else None  # dispatched asynchronously: renders while this batch is written
            tr = time.perf_counter()
            out = jax.device_get(pending)
            tw = time.perf_counter()
            render_wait += tw - tr
            for j in range(min(B, n - k * B)):
                i = k * B + j
                t_ns = int(cam_t_ns[i])
                for c, name in enumerate(CAMERAS):
                    img, dep, boxes, visible = (a[j] for a in out[c])
                    writer.write_frame(name, t_ns, img)
                    if config.depth:
                        writer.write_frame(f"depth{c}", t_ns, dep)
                    for tid in np.flatnonzero(visible > 0):
                        rows.append((t_ns, name, int(tid), int(class_id[tid]), boxes[tid],
                                     int(visible[tid]), positions[i, tid]))
            write_wait += time.perf_counter() - tw
            bar.update(min(B, n - k * B))
            pending = nxt
    finally:
        bar.close()

    tw = time.perf_counter()
    if config.targets:
        writer.write_targets(_labels(rows, class_names))
    write_wait += time.perf_counter() - tw
    timings["render"] = render_wait
    timings["write_wait"] = write_wait
    info = {
        "counts": {"frames": n, "target_rows": len(rows) if config.targets else 0},
        "scene": {"seed": scene_seed, "n_targets": n_targets,
                  "target_class_ids": class_id.tolist(), "class_names": list(class_names),
                  "room_lo": np.asarray(scn.room_lo).tolist(),
                  "room_hi": np.asarray(scn.room_hi).tolist(),
                  "flight_bounds_lo": np.asarray(lo).tolist(),
                  "flight_bounds_hi": np.asarray(hi).tolist()},
    }
    return info, timings


def _labels(rows: list[tuple], class_names: tuple[str, ...]) -> TargetLabels:
    m = len(rows)
    cols = list(zip(*rows, strict=True)) if rows else [()] * 7
    return TargetLabels(
        t_ns=np.asarray(cols[0], dtype=np.int64),
        camera=np.asarray(cols[1], dtype=str),
        track_id=np.asarray(cols[2], dtype=np.int64),
        class_id=np.asarray(cols[3], dtype=np.int64),
        box=np.asarray(cols[4], dtype=np.float64).reshape(m, 4),
        visible_pixels=np.asarray(cols[5], dtype=np.int64),
        position=np.asarray(cols[6], dtype=np.float64).reshape(m, 3),
        class_names=class_names,
    )


def _calib_dict(calib) -> dict[str, Any]:
    d = dataclasses.asdict(calib)
    return {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray | tuple) else v)
            for k, v in d.items()}
