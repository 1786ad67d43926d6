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
4. the followed box: of the detections less the parts of a larger box
   (:func:`~uavcal_jax.track.associate.contained_duplicates`), the one that overlaps the
   previous followed box most (IoU at least
   ``associate.min_iou``); at the start, and after ``associate.max_missed`` frames without one,
   the highest-scoring box of ``detect.follow_class``;
5. located from the depth image (:func:`uavcal_jax.track.locate.locate_box`) with the pose of
   the mode: the VIO's (``pose="vio"``) or the true one (``pose="true"``);
6. one step of the target filter (the same step :func:`uavcal_jax.track.filter.run_filter`
   scans, jitted alone);
7. one step of the follow law (:func:`uavcal_jax.track.follow.follow_step`) from the pose's
   position;
8. the kinematic drone (:mod:`uavcal_jax.sim.drone_model`) flies towards that set-point until
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

One module, over 450 lines: its job is one closed-loop flight, and its parts (the drone's
IMU written as it flies, the per-frame render-pose-detect-locate-filter-follow loop, and the
metrics over the flight, aligned to the truth) share the flight's state and its frames;
split, each would take a dozen arguments of the others' internals.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc_rig import euroc_imu_mounting
from uavcal_jax.data.sequence import GroundTruth, ImuData
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.errors import DataError
from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.pipeline.detectors import Detector
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.run_metrics import RUN_ALIGNMENT, statistics
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim import render, scene
from uavcal_jax.sim.config import CAMERAS, SimConfig, camera_calibrations, sensor_model, stage_seeds
from uavcal_jax.sim.drone_model import DroneConfig, fly, hover_state, imu_samples
from uavcal_jax.sim.frames import CameraEffects, make_frame_renderer
from uavcal_jax.sim.ground_target import GroundPath, ground_track, scene_with_track
from uavcal_jax.sim.imu_synth import imu_noise
from uavcal_jax.sim.simulate import imu_calibration
from uavcal_jax.track import (
    LOST,
    TRACKING,
    UNSEEN,
    AssociateConfig,
    Setpoint,
    contained_duplicates,
    cut_by_border,
    follow_step,
    locate_box,
)
from uavcal_jax.track import filter as target_filter
from uavcal_jax.track.associate import box_iou
from uavcal_jax.track.box_model import border_covariance, box_centre_candidates
from uavcal_jax.track.follow import wrap_angle
from uavcal_jax.track.heading import (
    heading_from_velocity,
    heading_spread,
    heading_step,
    uniform_belief,
)
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.run import one_blas_thread
from uavcal_jax.vio.trajectory_metrics import ate

__all__ = ["POSE_MODES", "STAGES", "ClosedLoopConfig", "ClosedLoopResult", "fly_closed_loop",
           "label_detections"]

#: Where the pipeline takes the drone's pose from.
POSE_MODES = ("vio", "true")
#: Timed stages, milliseconds per frame.
STAGES = ("render", "vio", "detect", "locate", "filter", "follow", "drone")


@dataclasses.dataclass(frozen=True)
class ClosedLoopConfig:
    """One closed-loop flight.

    Attributes:
        pose: ``"vio"`` or ``"true"`` (:data:`POSE_MODES`).
        duration: seconds of frames (from ``lead_s``).
        lead_s: seconds of hover IMU before the first frame (the VIO levels on them).
        resolution: ``(width, height)`` of the frames (EuRoC's lenses, scaled).
        camera_pitch_deg: the stereo rig below the quadrotor's forward axis, degrees.
        camera_rate_hz, imu_rate_hz: frame and IMU rates (the IMU a multiple of the frames).
        seed: the scene, the IMU noise and the camera noise.
        imu_noise: EuRoC's IMU noise and turn-on biases (false: exact IMU).
        min_visible_pixels: the target counts as in view (and as a label detection) from this
            many visible pixels in the left image.
        path: the car's scripted path (it starts at the origin heading +x).
        drone: the kinematic drone's limits and gains.
        run: the pipeline's settings (``uavcal run``'s :class:`RunConfig`: detection, locate,
            filter, follow, VIO, association).
    """

    pose: str = "vio"
    duration: float = 30.0
    lead_s: float = 0.5
    resolution: tuple[int, int] = (376, 240)
    camera_pitch_deg: float = 30.0
    camera_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    seed: int = 0
    imu_noise: bool = True
    min_visible_pixels: int = 40
    path: GroundPath = GroundPath()
    drone: DroneConfig = DroneConfig()
    run: RunConfig = RunConfig()

    def __post_init__(self):
        object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
        if self.pose not in POSE_MODES:
            raise ValueError(f"pose must be one of {POSE_MODES}, got {self.pose!r}")
        if not self.duration > 0 or self.lead_s < 0:
            raise ValueError("duration must be > 0 and lead_s >= 0")
        ratio = self.imu_rate_hz / self.camera_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise ValueError("imu_rate_hz must be a whole multiple of camera_rate_hz")
        if abs(self.drone.rate_hz - self.imu_rate_hz) > 1e-9:
            raise ValueError("the drone integrates at the IMU rate: drone.rate_hz must equal "
                             "imu_rate_hz")


@dataclasses.dataclass(frozen=True)
class ClosedLoopResult:
    """A flight, per frame ``F`` (world = the true world; VIO quantities aligned to it).

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
        metrics: the figures (:func:`_metrics`).
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


@functools.partial(jax.jit, static_argnames="config")
def _filter_step(carry, t, z, R, valid, config):
    """One frame of :func:`uavcal_jax.track.filter.run_filter` (its own step function)."""
    return target_filter._step(config, carry, (t, z, R, valid))


def _filter_start(dtype) -> target_filter._Carry:
    return target_filter._Carry(x=jnp.zeros(6, dtype), P=jnp.eye(6, dtype=dtype),
                                t=jnp.zeros((), dtype), t_used=jnp.asarray(jnp.nan, dtype),
                                active=jnp.asarray(False), gated_run=jnp.zeros((), jnp.int32))


def _yaw_of(R_WQ: np.ndarray) -> float:
    return float(np.arctan2(R_WQ[1, 0], R_WQ[0, 0]))


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


class _Chooser:
    """Step 4 of the module docstring: the followed box, frame after frame."""

    def __init__(self, class_id: int, config: AssociateConfig):
        self.class_id, self.config = class_id, config
        self.box: np.ndarray | None = None
        self.missed = 0

    def __call__(self, det: ImageDetections) -> tuple[np.ndarray | None, float]:
        # a box of a part of a larger one is not a candidate (as in uavcal run's association)
        whole = contained_duplicates(det.boxes, det.classes, self.config.merge_contained)
        mine = np.flatnonzero((np.asarray(det.classes) == self.class_id) & whole)
        pick = None
        if mine.size and self.box is not None:
            iou = box_iou(self.box[None], det.boxes[mine])[0]
            if iou.max() >= self.config.min_iou:
                pick = mine[int(np.argmax(iou))]
        if pick is None and mine.size and (self.box is None
                                           or self.missed >= self.config.max_missed):
            pick = mine[int(np.argmax(det.scores[mine]))]
        if pick is None:
            self.missed += 1
            return None, float("nan")
        self.box, self.missed = np.asarray(det.boxes[pick], np.float64), 0
        return self.box, float(det.scores[pick])


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
    run = config.run
    rate_ratio = int(round(config.imu_rate_hz / config.camera_rate_hz))
    dt_imu, dt_frame = 1.0 / config.imu_rate_hz, 1.0 / config.camera_rate_hz
    sim = SimConfig(resolution=config.resolution, camera_pitch_deg=config.camera_pitch_deg,
                    seed=config.seed, camera_rate_hz=config.camera_rate_hz,
                    imu_rate_hz=config.imu_rate_hz, blur_samples=1)
    seeds = stage_seeds(config.seed)
    calibs = camera_calibrations(sim)
    cam0 = calibs[CAMERAS[0]]
    class_names = scene.CLASS_NAMES if detector is None else tuple(detector.class_names)
    if run.detect.follow_class not in class_names:
        raise DataError(f"detect.follow_class={run.detect.follow_class!r} is not a class of the "
                        f"detector (its classes: {', '.join(class_names)})")
    follow_id = list(class_names).index(run.detect.follow_class)

    # the world: the car's track from the origin heading +x; the drone behind it
    n_frames = int(np.floor(config.duration * config.camera_rate_hz + 1e-9)) + 1
    lead = int(round(config.lead_s * config.imu_rate_hz / rate_ratio)) * rate_ratio
    n_imu = lead + (n_frames - 1) * rate_ratio + 1
    scene_s = n_imu * dt_imu + 1.0
    track = ground_track(config.path, scene_s)
    fcfg = run.follow
    start_z_guess = 0.8 + fcfg.height
    margin = fcfg.distance + 1.5
    flight_lo = np.array([*(track[:, :2].min(0) - margin), 0.0])
    flight_hi = np.array([*(track[:, :2].max(0) + margin), start_z_guess + 1.0])
    scn = scene_with_track(track, flight_lo, flight_hi, seeds["scene"])
    target_z = float(np.asarray(scn.targets.z)[0])
    target_class = np.asarray(scn.targets.class_id, np.int64)
    start = hover_state([track[0, 0] - fcfg.distance, track[0, 1], target_z + fcfg.height],
                        float(track[0, 2]))

    # the IMU stream, filled as the drone flies (the VIO keeps a reference to these arrays)
    R_QB = euroc_imu_mounting()
    t_imu = np.arange(n_imu, dtype=np.int64) * int(round(1e9 * dt_imu))
    imu = ImuData(t_ns=t_imu, gyro=np.zeros((n_imu, 3)), accel=np.zeros((n_imu, 3)))
    noise = imu_noise(n_imu, dt_imu, EUROC_ADIS16448, seeds["imu"]) if config.imu_noise else None

    def write_imu(flight, k0: int):
        """Samples k0 .. k0 + n - 1 from a flight that started at sample k0, and the
        accelerometer of sample k0 + n (known from the state alone)."""
        gyro_q, accel_q = imu_samples(flight, dt_imu)
        n = gyro_q.shape[0]
        end_accel = R_QB.T @ (flight.R_WQ[-1].T @ (flight.a[-1] - np.asarray(GRAVITY_W)))
        imu.gyro[k0:k0 + n] = gyro_q @ R_QB  # R_QB^T g, row-wise
        imu.accel[k0:k0 + n] = accel_q @ R_QB
        imu.accel[k0 + n] = end_accel
        imu.gyro[k0 + n] = imu.gyro[k0 + n - 1] if n else 0.0  # finite stand-in, replaced
        if noise is not None:
            sl = slice(k0, k0 + n + 1)
            imu.gyro[sl] += noise["bias_gyro"][sl] + noise["white_gyro"][sl]
            imu.accel[sl] += noise["bias_accel"][sl] + noise["white_accel"][sl]

    vio = StereoVio(cam0, calibs[CAMERAS[1]], imu_calibration(sim), imu, run.vio) \
        if config.pose == "vio" else None

    # the renderer: sensor noise, no motion blur (the sub-exposure poses would be in the future)
    effects = CameraEffects(sensor=sensor_model(sim), noise=True, blur_samples=1)
    renderer = make_frame_renderer("gray", scn.n_targets, effects)
    lenses = [camera_model.from_calibration(calibs[n]) for n in CAMERAS]
    bundles = [jax.tree_util.tree_map(jnp.asarray, render.ray_bundle(lens)) for lens in lenses]
    lenses32 = [lens.astype(jnp.float32) for lens in lenses]
    camera = lenses[0]
    T_BS = [np.asarray(calibs[n].T_BS, np.float64) for n in CAMERAS]
    key = jax.random.PRNGKey(seeds["camera"])
    eye = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (1, 1, 4, 4))
    extent = run.detect.target_extent()
    half_size = run.detect.target_half_size()
    belief, t_belief = uniform_belief(), None  # over the box model's candidate headings
    velocity_heading = np.nan  # the filter's, before this frame

    # hover before the first frame
    flight = fly(start, start.p, start.yaw, lead, config.drone)
    write_imu(flight, 0)
    state = flight.state()

    chooser = _Chooser(follow_id, run.associate)
    carry = _filter_start(jnp.zeros(()).dtype)
    sp_pose: Setpoint | None = None  # the follow law's set-point, in the pose's world
    sp_true, yaw_true = start.p.copy(), start.yaw
    F = n_frames
    rec = {k: np.full((F, 3), np.nan) for k in ("drone", "vio_raw", "target", "raw_pose",
                                                "filtered_pose", "setpoint")}
    rec_R, true_R = np.full((F, 3, 3), np.nan), np.zeros((F, 3, 3))
    drone_yaw, sp_yaw = np.zeros(F), np.zeros(F)
    in_view, status = np.zeros(F, bool), np.full(F, UNSEEN, np.int32)
    unmeasured = np.full(F, "", dtype=object)  # why a frame has no measurement
    T_err_all = np.tile(np.eye(4), (F, 1, 1))
    ms = {s: np.zeros(F) for s in STAGES}
    bar = progress_bar(total=F, desc=f"closed loop ({config.pose} pose)", enabled=show_progress,
                       unit="frame")
    with one_blas_thread():
        for j in range(F):
            k_imu = lead + j * rate_ratio
            t_scene = k_imu * dt_imu
            t_rel = j * dt_frame
            R_WQ = flight.R_WQ[-1]
            T_WB = _pose(R_WQ @ R_QB, state.p)
            rec["drone"][j], drone_yaw[j], true_R[j] = state.p, state.yaw, T_WB[:3, :3]

            # 1. render
            c0 = time.perf_counter()
            T0, T1 = (jnp.asarray((T_WB @ T)[None], jnp.float32) for T in T_BS)
            out = renderer(scn, bundles[0], bundles[1], *lenses32, T0, T1,
                           jnp.asarray([t_scene], jnp.float32), eye, eye,
                           jnp.asarray([j], jnp.int32), key)
            (img0, dep0, boxes0, vis0), (img1, _, _, _) = jax.device_get(out)
            left, right, depth = img0[0], img1[0], dep0[0].astype(np.float32) * 1e-3
            ms["render"][j] = 1e3 * (time.perf_counter() - c0)
            truth = np.asarray(scene.target_states(scn, t_scene)[0], np.float64)[0]
            rec["target"][j] = truth
            in_view[j] = int(vis0[0][0]) >= config.min_visible_pixels

            # 2. detect, choose (first: the VIO's front end leaves the boxes out)
            c0 = time.perf_counter()
            if detector is None:
                det = masked = label_detections(boxes0[0], vis0[0], target_class,
                                                config.min_visible_pixels)
            else:
                found = detector([np.repeat(left[..., None], 3, axis=-1)], [j])[0]
                masked = found.above(run.detect.detector_threshold())
                det = found.above(run.detect.score_threshold)
            box, _ = chooser(det)
            ms["detect"][j] = 1e3 * (time.perf_counter() - c0)

            # 3. the pose
            c0 = time.perf_counter()
            if vio is not None:
                est = vio.process(int(t_imu[k_imu]), left, right,
                                  masked.boxes if run.detect.mask_vio else None)
                ok = est.has_pose and np.all(np.isfinite(est.position))
                T_pose = _pose(est.rotation, est.position) if ok else None
            else:
                T_pose = T_WB
            ms["vio"][j] = 1e3 * (time.perf_counter() - c0)
            if T_pose is not None:
                rec["vio_raw"][j] = T_pose[:3, 3]
                rec_R[j] = T_pose[:3, :3]
                T_err_all[j] = T_WB @ np.linalg.inv(T_pose)

            # 5. locate
            c0 = time.perf_counter()
            z, R, valid = np.zeros(3), np.eye(3), False
            if box is None:
                unmeasured[j] = "not detected"
            elif T_pose is None:
                unmeasured[j] = "no pose"
            elif not (half_size is not None and run.detect.locate_cut) and cut_by_border(
                    box, config.resolution, run.detect.border_px):
                unmeasured[j] = "cut by the border"
            else:
                loc = locate_box(np.asarray(box, np.float32), depth, camera, T_BS[0], T_pose,
                                 extent, run.locate)
                unmeasured[j] = "" if bool(loc.located) else "not located"
                if bool(loc.located):
                    z, R, valid = np.asarray(loc.point), np.asarray(loc.covariance), True
                    if half_size is not None:  # the front surface -> the box's centre
                        centres, mismatch = box_centre_candidates(
                            z, T_pose @ T_BS[0], np.asarray(half_size),
                            np.asarray(box, np.float64), camera, run.locate)
                        belief = heading_step(belief, 0.0 if t_belief is None else
                                              t_rel - t_belief, np.asarray(mismatch),
                                              velocity_heading, run.heading)
                        t_belief = t_rel
                        chosen = int(np.argmax(belief))
                        R = R + heading_spread(np.asarray(centres), belief, chosen) + \
                            border_covariance(box, config.resolution, (T_pose @ T_BS[0])[:3, :3],
                                              half_size, run.detect.border_px)
                        z = np.asarray(centres[chosen], np.float64)
                    rec["raw_pose"][j] = z
            ms["locate"][j] = 1e3 * (time.perf_counter() - c0)

            # 6. filter
            c0 = time.perf_counter()
            carry, fout = _filter_step(carry, jnp.asarray(t_rel, carry.x.dtype),
                                       jnp.asarray(z, carry.x.dtype), jnp.asarray(R, carry.x.dtype),
                                       jnp.asarray(valid), run.filter)
            status[j] = int(fout.status)
            if bool(fout.gated):
                unmeasured[j] = "gated"
            target_pos = np.asarray(fout.position, np.float64)
            velocity_heading = float(heading_from_velocity(
                np.asarray(fout.velocity)[None], run.heading.min_speed)[0])
            rec["filtered_pose"][j] = target_pos
            ms["filter"][j] = 1e3 * (time.perf_counter() - c0)

            # 7. follow (in the pose's world), mapped to the true world for the drone
            c0 = time.perf_counter()
            v_ff = np.zeros(3)
            if T_pose is not None:
                p_pose = T_pose[:3, 3]
                if sp_pose is None:  # start from the drone's own pose
                    sp_pose = Setpoint(p_pose.copy(), _yaw_of(T_pose[:3, :3] @ R_QB.T))
                known = status[j] != UNSEEN
                nxt = follow_step(sp_pose, target_pos, known, p_pose, dt_frame, fcfg)
                nxt = Setpoint(np.asarray(nxt.position, np.float64), float(nxt.yaw))
                T_err = T_err_all[j]
                v_ff = T_err[:3, :3] @ (nxt.position - sp_pose.position) / dt_frame
                sp_pose = nxt
                sp_true = T_err[:3, :3] @ nxt.position + T_err[:3, 3]
                yaw_true = nxt.yaw + _yaw_of(T_err[:3, :3])
            rec["setpoint"][j], sp_yaw[j] = sp_true, yaw_true
            ms["follow"][j] = 1e3 * (time.perf_counter() - c0)

            # 8. fly to the next frame
            c0 = time.perf_counter()
            if j + 1 < F:
                flight = fly(state, sp_true, yaw_true, rate_ratio, config.drone, velocity_ff=v_ff)
                write_imu(flight, k_imu)
                state = flight.state()
            ms["drone"][j] = 1e3 * (time.perf_counter() - c0)
            bar.update(1)
            bar.set_postfix_str(f"{status_name(status[j])} view={int(in_view[j])}",
                                refresh=False)
    bar.close()

    t = np.arange(F) * dt_frame
    following = t + config.lead_s >= config.path.wait_s
    return _result(config, detector_name, t, t_imu[lead::rate_ratio][:F], rec, rec_R, true_R,
                   drone_yaw, in_view, status, sp_yaw, following, ms, unmeasured)


def status_name(code: int) -> str:
    return target_filter.STATUS_NAMES[int(code)]


def _episodes(mask: np.ndarray, dt: float) -> list[float]:
    """Durations (seconds) of the runs of True in ``mask``."""
    out, run = [], 0
    for m in list(mask) + [False]:
        if m:
            run += 1
        elif run:
            out.append(run * dt)
            run = 0
    return out


def _result(config, detector_name, t, t_ns, rec, rec_R, true_R, drone_yaw, in_view, status,
            sp_yaw, following, ms, unmeasured) -> ClosedLoopResult:
    """Align the pose's world to the truth and compute the metrics."""
    fcfg = config.run.follow
    dt = 1.0 / config.camera_rate_hz
    have = np.all(np.isfinite(rec["vio_raw"]), axis=1)
    align_R, align_t, ate_m = np.eye(3), np.zeros(3), None
    if config.pose == "vio" and have.sum() >= 3:
        est = _trajectory(t_ns[have], rec["vio_raw"][have], rec_R[have])
        gt = _trajectory(t_ns[have], rec["drone"][have], true_R[have])
        try:
            res = ate(est, gt, alignment=RUN_ALIGNMENT)
        except DataError:
            res = ate(est, gt, alignment="origin")
        align_R, align_t = res.alignment.rotation, res.alignment.translation
        s = res.translation
        ate_m = {"rmse": s.rmse, "mean": s.mean, "median": s.median, "max": s.max,
                 "alignment": res.alignment.method}

    def aligned(points):
        return points @ align_R.T + align_t

    vio_pos = aligned(rec["vio_raw"]) if config.pose == "vio" else rec["vio_raw"]
    raw = aligned(rec["raw_pose"])
    filtered = aligned(rec["filtered_pose"])
    target = rec["target"]
    drone = rec["drone"]
    rel = target[:, :2] - drone[:, :2]
    dist = np.linalg.norm(rel, axis=1)
    w = following
    dist_err = np.abs(dist - fcfg.distance)
    height_err = drone[:, 2] - (target[:, 2] + fcfg.height)
    yaw_err = np.asarray(wrap_angle(drone_yaw - np.arctan2(rel[:, 1], rel[:, 0])))
    raw_err = np.linalg.norm(raw - target, axis=1)
    filt_err = np.linalg.norm(filtered - target, axis=1)
    seen = np.cumsum(status == TRACKING) > 0
    gaps = _episodes(w & seen & (status != TRACKING), dt)
    lost = _episodes(w & (status == LOST), dt)
    warm = config.run.warmup_frames
    metrics = {
        "pose": config.pose, "detector": detector_name, "frames": int(len(t)),
        "evaluated_frames": int(w.sum()),
        "window": f"from the car's start (t >= {config.path.wait_s:g} s of scene time)",
        "distance_error_m": _stats(dist_err[w]),
        "height_error_m": _stats(np.abs(height_err[w])),
        "yaw_error_deg": _stats(np.degrees(np.abs(yaw_err[w]))),
        "in_view_fraction": float(np.mean(in_view[w])) if w.any() else None,
        "in_view_fraction_all": float(np.mean(in_view)),
        "measured_fraction": float(np.mean(status[w] == TRACKING)) if w.any() else None,
        "losses": {"count": len(gaps), "durations_s": gaps,
                   "longest_s": max(gaps, default=0.0),
                   "lost_status_episodes_s": lost,
                   "frames_by_reason": dict(collections.Counter(
                       str(r) for r in unmeasured[w & seen & (status != TRACKING)] if r))},
        "localisation_rmse_m": {"raw": _stats(raw_err[w]), "filtered": _stats(filt_err[w])},
        "vio_ate_m": ate_m,
        "ms_per_frame": {s: {"mean": float(np.mean(v[warm:])) if len(v) > warm else None,
                             "first": float(v[0])} for s, v in ms.items()},
    }
    metrics["ms_per_frame"]["total"] = {
        "mean": float(np.mean(sum(ms[s] for s in STAGES)[warm:])) if len(t) > warm else None}
    return ClosedLoopResult(config, detector_name, t, drone, drone_yaw, vio_pos, target, in_view,
                            raw, filtered, status, rec["setpoint"], sp_yaw, following, metrics)


def _trajectory(t_ns: np.ndarray, position: np.ndarray, R: np.ndarray) -> GroundTruth:
    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]  # w x y z
    return GroundTruth(np.asarray(t_ns, np.int64), np.asarray(position, np.float64), q)


def _stats(errors) -> dict | None:
    s = statistics(errors)
    return None if s is None else {k: s[k] for k in ("mean", "median", "rmse", "max", "count")}
