"""Closed-loop following in the simulator (RPEOD section 6.3's Gazebo test): the drone flies
the pipeline's own set-points, and the frames are rendered from where it actually is.

Per frame ``j`` (20 Hz; scene time ``t_j`` in seconds since the IMU stream's first sample):

1. render cam0, cam1 and cam0's depth from the drone's *true* pose at ``t_j`` (EuRoC's rig,
   pitched ``camera_pitch_deg`` below the quadrotor's forward axis; the scripted car of
   :mod:`uavcal_jax.sim.ground_target` where it is at ``t_j``);
2. the detector on the left image (the shipped network, a trained run, or the renderer's
   own target boxes, ``labels``);
3. the stereo VIO (:class:`~uavcal_jax.vio.estimator.StereoVio`) on the pair, with the IMU the
   drone has produced up to ``t_j``, its front end tracking nothing inside the detections
   (``detect.mask_vio``);
4. one step of ``uavcal run``'s target stage,
   :meth:`~uavcal_jax.pipeline.tracker.TargetTracker.step` (association, the choice of the
   followed car, its box located from the depth image, one filter step and one step of the
   follow law) with the pose of the mode: the VIO's (``pose="vio"``) or the true one
   (``pose="true"``);
5. the kinematic drone (:mod:`uavcal_jax.sim.drone_model`) flies towards that set-point until
   ``t_{j+1}`` at the IMU rate, with the set-point's velocity as feed-forward, and its IMU
   samples (EuRoC's ADIS16448 noise and turn-on biases, :func:`~uavcal_jax.sim.imu_synth.
   imu_noise`) are written into the stream the VIO reads.

The VIO's world is not the true world: with ``pose="vio"`` the set-point (VIO world) is flown
as the drone's controller would fly it on the VIO's estimate, i.e. mapped into the true world
by the current estimation error ``T_true T_vio^-1`` (a drifting VIO makes the drone drift).
Until the VIO has a pose the drone hovers. The IMU stream is allocated for the whole flight
and filled as the drone flies: :class:`~uavcal_jax.vio.imu_slice.ImuStream` keeps a reference
and reads only the samples up to the frame being processed (the sample at ``t_j`` itself
is used only for its accelerometer, which is known at ``t_j``).

Frames: ``Q`` the quadrotor (x forward, z up, what the drone model flies), ``B`` the IMU (the
body frame of the VIO and of the camera extrinsics; EuRoC's mounting ``R_QB``).

The world (scene, IMU stream, renderer) is :mod:`uavcal_jax.pipeline.closed_loop_world`, the
figures :mod:`uavcal_jax.pipeline.closed_loop_metrics`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.pipeline.closed_loop_metrics import align_to_truth, flight_metrics
from uavcal_jax.pipeline.closed_loop_world import World, build_world
from uavcal_jax.pipeline.detectors import Detector
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.targets import class_id_of
from uavcal_jax.pipeline.tracker import TRACKER_STAGES, TargetEstimate, TargetTracker
from uavcal_jax.pipeline.tracker_locate import FrameSensors, Localizer
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim import scene
from uavcal_jax.sim.config import CAMERAS, LOW_RESOLUTION, SimConfig
from uavcal_jax.sim.drone_model import DroneConfig, fly
from uavcal_jax.sim.ground_target import GroundPath
from uavcal_jax.sim.simulate import imu_calibration
from uavcal_jax.track import UNSEEN
from uavcal_jax.track import filter as target_filter
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.run import one_blas_thread

__all__ = ["POSE_MODES", "STAGES", "ClosedLoopConfig", "ClosedLoopResult", "fly_closed_loop",
           "label_detections"]

#: Where the pipeline takes the drone's pose from.
POSE_MODES = ("vio", "true")
#: Timed stages, milliseconds per frame.
STAGES = ("render", "detect", "vio", *TRACKER_STAGES, "drone")


@dataclasses.dataclass(frozen=True)
class ClosedLoopConfig:
    """One closed-loop flight.

    Attributes:
        pose: ``"vio"`` or ``"true"`` (:data:`POSE_MODES`).
        sim: the simulated sensors (:class:`~uavcal_jax.sim.config.SimConfig`): ``duration``
            (seconds of frames, from ``lead_s``), ``resolution`` (EuRoC's lenses, scaled),
            ``camera_pitch_deg`` (the stereo rig below the quadrotor's forward axis),
            ``camera_rate_hz`` and ``imu_rate_hz`` (the IMU a multiple of the frames),
            ``seed`` (the scene, the IMU noise and the camera noise), ``imu_noise`` (EuRoC's
            IMU noise and turn-on biases; false: exact IMU), ``exposure_ms`` and ``gain``.
            Rendered without motion blur: ``blur_samples`` must be 1.
        lead_s: seconds of hover IMU before the first frame (the VIO levels on them).
        start_offset: (3,) metres (world: x along the car's start heading, z up) from the
            stand-off point behind the car where the drone starts.
        min_visible_pixels: the target counts as in view (and as a label detection) from this
            many visible pixels in the left image.
        path: the car's scripted path (it starts at the origin heading +x).
        drone: the kinematic drone's limits and gains.
        run: the pipeline's settings (``uavcal run``'s :class:`RunConfig`: detection, locate,
            filter, follow, VIO, association).
    """

    pose: str = "vio"
    sim: SimConfig = SimConfig(duration=30.0, resolution=LOW_RESOLUTION, camera_pitch_deg=30.0,
                               blur_samples=1)
    lead_s: float = 0.5
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    min_visible_pixels: int = 40
    path: GroundPath = GroundPath()
    drone: DroneConfig = DroneConfig()
    run: RunConfig = RunConfig()

    def __post_init__(self):
        object.__setattr__(self, "start_offset", tuple(float(v) for v in self.start_offset))
        if self.pose not in POSE_MODES:
            raise ValueError(f"pose must be one of {POSE_MODES}, got {self.pose!r}")
        self.sim.validate()
        if self.lead_s < 0:
            raise ValueError("lead_s must be >= 0")
        if self.sim.blur_samples != 1:
            raise ValueError("the closed loop renders without motion blur (its sub-exposure "
                             "poses would be in the future): sim.blur_samples must be 1")
        ratio = self.sim.imu_rate_hz / self.sim.camera_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise ValueError("sim.imu_rate_hz must be a whole multiple of sim.camera_rate_hz")
        if abs(self.drone.rate_hz - self.sim.imu_rate_hz) > 1e-9:
            raise ValueError("the drone integrates at the IMU rate: drone.rate_hz must equal "
                             "sim.imu_rate_hz")


@dataclasses.dataclass(frozen=True)
class ClosedLoopResult:
    """A flight, per frame ``F`` (world = the true world; the pose's quantities aligned to it).

    Attributes:
        config: the flight's settings.  detector: what detected (``shipped``, ``labels`` or a
            run folder).
        t: (F,) seconds since the first frame.
        drone: (F, 3) true body position.  drone_yaw: (F,) true quadrotor heading.
        vio: (F, 3) the VIO's position aligned to the truth (NaN without a pose).
        target: (F, 3) true target centre.  in_view: (F,) bool.
        raw: (F, 3) the located point (aligned; NaN where none).
        filtered: (F, 3) the filter's position (aligned; NaN while unseen).
        status: (F,) filter status codes.
        setpoint: (F, 3) the set-point flown, true world; setpoint_yaw (F,).
        following: (F,) bool: the car has started (the metrics' window).
        metrics: the figures (:func:`~uavcal_jax.pipeline.closed_loop_metrics.flight_metrics`,
            with ``pose``, ``detector`` and ``vio_ate_m``).
    """

    config: ClosedLoopConfig
    detector: str
    t: np.ndarray
    drone: np.ndarray
    drone_yaw: np.ndarray
    vio: np.ndarray
    target: np.ndarray
    in_view: np.ndarray
    raw: np.ndarray
    filtered: np.ndarray
    status: np.ndarray
    setpoint: np.ndarray
    setpoint_yaw: np.ndarray
    following: np.ndarray
    metrics: dict


def label_detections(boxes: np.ndarray, visible: np.ndarray, class_id: np.ndarray,
                     min_visible_pixels: int) -> ImageDetections:
    """The renderer's target boxes (n, 4) with at least ``min_visible_pixels`` visible (n,)
    pixels, as detections of score 1 and class ``class_id`` (n,) (the simulator's labels)."""
    keep = np.asarray(visible) >= min_visible_pixels
    return ImageDetections(np.asarray(boxes, np.float64)[keep].reshape(-1, 4),
                           np.ones(int(keep.sum())), np.asarray(class_id, np.int64)[keep])


def _yaw_of(R_WQ: np.ndarray) -> float:
    return float(np.arctan2(R_WQ[1, 0], R_WQ[0, 0]))


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def status_name(code: int) -> str:
    return target_filter.STATUS_NAMES[int(code)]


class _Flight:
    """The flight's state between frames: the drone, the set-point flown (true world) and
    the tracker's last (pose world), and the per-frame record."""

    def __init__(self, config: ClosedLoopConfig, world: World, detector: Detector | None):
        self.config, self.world, self.detector = config, world, detector
        run = config.run
        class_names = scene.CLASS_NAMES if detector is None else tuple(detector.class_names)
        left = world.calibrations[CAMERAS[0]]
        self.tracker = TargetTracker(run, class_id_of(class_names, run.detect.follow_class),
                                     Localizer(run, "depth", left))
        self.vio = StereoVio(left, world.calibrations[CAMERAS[1]], imu_calibration(config.sim),
                             world.imu, run.vio) if config.pose == "vio" else None
        self.T_BS = [np.asarray(world.calibrations[n].T_BS, np.float64) for n in CAMERAS]
        start = world.start  # hover before the first frame
        self.flight = fly(start, start.p, start.yaw, world.lead, config.drone)
        world.write_imu(self.flight, 0)
        self.state = self.flight.state()
        self.sp_true, self.yaw_true, self.sp_pose = start.p.copy(), start.yaw, None
        F = world.n_frames
        self.rec = {k: np.full((F, 3), np.nan) for k in ("drone", "pose", "target", "raw",
                                                         "filtered", "setpoint")}
        self.pose_R, self.true_R = np.full((F, 3, 3), np.nan), np.zeros((F, 3, 3))
        self.drone_yaw, self.sp_yaw = np.zeros(F), np.zeros(F)
        self.in_view, self.status = np.zeros(F, bool), np.full(F, UNSEEN, np.int32)
        self.unmeasured = np.full(F, "", dtype=object)  # why a frame has no measurement
        self.ms = {s: np.zeros(F) for s in STAGES}

    def frame(self, j: int) -> None:
        """Render, detect, pose, track, fly frame ``j`` (the module docstring's steps)."""
        cfg, world, run = self.config, self.world, self.config.run
        k_imu = world.lead + j * world.rate_ratio
        t_scene = k_imu * world.dt_imu
        T_WB = _pose(self.flight.R_WQ[-1] @ world.R_QB, self.state.p)
        self.rec["drone"][j], self.drone_yaw[j], self.true_R[j] = self.state.p, \
            self.state.yaw, T_WB[:3, :3]
        c0 = time.perf_counter()
        left, right, depth, boxes, visible = world.render(T_WB, t_scene, j)
        self.rec["target"][j] = world.target_position(t_scene)
        self.in_view[j] = int(visible[0]) >= cfg.min_visible_pixels
        c1 = time.perf_counter()
        det, masked = self._detect(j, left, boxes, visible)
        c2 = time.perf_counter()
        T_pose = T_WB
        if self.vio is not None:  # the VIO's front end leaves the detections out
            est = self.vio.process(int(world.imu.t_ns[k_imu]), left, right,
                                   masked.boxes if run.detect.mask_vio else None)
            ok = est.has_pose and np.all(np.isfinite(est.position))
            T_pose = _pose(est.rotation, est.position) if ok else None
        c3 = time.perf_counter()
        estimate = self.tracker.step(j / cfg.sim.camera_rate_hz, det, T_pose,
                                     FrameSensors(depth=lambda: depth))
        self._record(j, estimate, T_pose)
        c4 = time.perf_counter()
        v_ff = self._setpoint(estimate.setpoint, T_WB, T_pose)
        self.rec["setpoint"][j], self.sp_yaw[j] = self.sp_true, self.yaw_true
        if j + 1 < world.n_frames:  # fly to the next frame
            self.flight = fly(self.state, self.sp_true, self.yaw_true, world.rate_ratio,
                              cfg.drone, velocity_ff=v_ff)
            world.write_imu(self.flight, k_imu)
            self.state = self.flight.state()
        c5 = time.perf_counter()
        for stage, ms in (("render", c1 - c0), ("detect", c2 - c1), ("vio", c3 - c2),
                          ("drone", c5 - c4)):
            self.ms[stage][j] = 1e3 * ms
        for stage in TRACKER_STAGES:
            self.ms[stage][j] = estimate.ms[stage]

    def _detect(self, j: int, left, boxes, visible) -> tuple[ImageDetections, ImageDetections]:
        """The detections (score-thresholded) and the VIO mask's (its lower threshold)."""
        run = self.config.run
        if self.detector is None:
            det = label_detections(boxes, visible, self.world.target_class,
                                   self.config.min_visible_pixels)
            return det, det
        found = self.detector([np.repeat(left[..., None], 3, axis=-1)], [j])[0]
        return found.above(run.detect.tracked_threshold()), \
            found.above(run.detect.detector_threshold())

    def _record(self, j: int, estimate: TargetEstimate, T_pose) -> None:
        if T_pose is not None:
            self.rec["pose"][j], self.pose_R[j] = T_pose[:3, 3], T_pose[:3, :3]
        located = estimate.located
        if located is None:
            self.unmeasured[j] = "not detected"
        elif not located.located:
            self.unmeasured[j] = located.reason
        else:
            self.rec["raw"][j] = located.point
        if bool(estimate.filtered.gated):
            self.unmeasured[j] = "gated"
        self.status[j] = int(estimate.filtered.status)
        self.rec["filtered"][j] = estimate.filtered.position

    def _setpoint(self, setpoint, T_WB, T_pose) -> np.ndarray:
        """The tracker's set-point (pose world) mapped into the true world by the pose's
        error ``T_true T_pose^-1`` (held without a pose); the feed-forward velocity (3,)."""
        if setpoint is None or T_pose is None:
            return np.zeros(3)
        previous = self.sp_pose if self.sp_pose is not None else self.tracker.start
        T_err = T_WB @ np.linalg.inv(T_pose)
        v_ff = T_err[:3, :3] @ (setpoint.position - previous.position) * \
            self.config.sim.camera_rate_hz
        self.sp_pose = setpoint
        self.sp_true = T_err[:3, :3] @ setpoint.position + T_err[:3, 3]
        self.yaw_true = setpoint.yaw + _yaw_of(T_err[:3, :3])
        return v_ff

    def result(self, detector_name: str) -> ClosedLoopResult:
        """Align the pose's world to the truth and compute the figures."""
        cfg, world, rec = self.config, self.world, self.rec
        F = world.n_frames
        t = np.arange(F) / cfg.sim.camera_rate_hz
        t_ns = world.imu.t_ns[world.lead::world.rate_ratio][:F]
        R, p, ate_m = np.eye(3), np.zeros(3), None
        if cfg.pose == "vio":
            R, p, ate_m = align_to_truth(t_ns, rec["pose"], self.pose_R, rec["drone"],
                                         self.true_R)
        vio, raw, filtered = (rec[k] @ R.T + p for k in ("pose", "raw", "filtered"))
        following = t + cfg.lead_s >= cfg.path.wait_s
        metrics = {"pose": cfg.pose, "detector": detector_name} | flight_metrics(
            follow=cfg.run.follow, dt=1.0 / cfg.sim.camera_rate_hz, window=following,
            window_text=f"from the car's start (t >= {cfg.path.wait_s:g} s of scene time)",
            drone=rec["drone"], drone_yaw=self.drone_yaw, target=rec["target"],
            in_view=self.in_view, raw=raw, filtered=filtered, status=self.status,
            unmeasured=self.unmeasured, ms=self.ms, warmup=cfg.run.warmup_frames) | {
            "vio_ate_m": ate_m}
        return ClosedLoopResult(cfg, detector_name, t, rec["drone"], self.drone_yaw, vio,
                                rec["target"], self.in_view, raw, filtered, self.status,
                                rec["setpoint"], self.sp_yaw, following, metrics)


def fly_closed_loop(config: ClosedLoopConfig, detector: Detector | None, detector_name: str,
                    show_progress: bool = False) -> ClosedLoopResult:
    """Fly one closed-loop flight (the module docstring).

    Args:
        config: :class:`ClosedLoopConfig`.
        detector: a network :class:`~uavcal_jax.pipeline.detectors.Detector`, or ``None`` for
            the renderer's own target boxes (:func:`label_detections`).
        detector_name: what ``detector`` is, for the report.
        show_progress: a progress bar on stderr.

    Raises:
        DataError: the detector does not know ``run.detect.follow_class``.
    """
    world = build_world(config.sim, config.path, config.run.follow, config.lead_s,
                        config.sim.duration, config.start_offset)
    flight = _Flight(config, world, detector)
    bar = progress_bar(total=world.n_frames, desc=f"closed loop ({config.pose} pose)",
                       enabled=show_progress, unit="frame")
    with one_blas_thread():
        for j in range(world.n_frames):
            flight.frame(j)
            bar.update(1)
            bar.set_postfix_str(f"{status_name(flight.status[j])} "
                                f"view={int(flight.in_view[j])}", refresh=False)
    bar.close()
    return flight.result(detector_name)
