"""The simulator's camera stage: render both cameras along a flight and queue the frames,
depth maps and target labels to an :class:`~uavcal_jax.data.euroc_writer.EurocWriter`.

Both EuRoC cameras (cam0, cam1) are rendered at ``T_WC = T_WB(t) @ T_BS`` at the frame times
(:func:`frame_times`: triggered on IMU samples, as in EuRoC, when the rates divide; or the
caller's timestamps), in a scene built around the flight. Depth ``depthN`` is cam N's z-depth
in uint16 millimetres (0 = no depth). Target labels (``target0``) list, for each frame and
camera, every target with visible pixels: the tight box around those pixels, their count, and
the target's 3D world position; ``target0/track.csv`` holds every target's world state at every
frame. ``SimConfig.follow_targets`` adds targets that move where cam0 looks
(:mod:`uavcal_jax.sim.follow_targets`).

The frames go through EuRoC's camera (:class:`CameraEffects`, on unless
``SimConfig.ideal_camera``): motion blur over the exposure from the trajectory's poses
(:mod:`uavcal_jax.sim.motion_blur`), then exposure x gain, shot and read noise and 8-bit
quantisation (:mod:`uavcal_jax.sim.sensor`), the noise keyed by the camera stage's seed, the
frame's index and the camera. Depth and labels are those of the mid-exposure pose, the frame's
timestamp.

Frames are rendered in fixed-size batches by one jitted function (compiled once; the last
batch is padded); the next batch is dispatched before this one is written, so PNG encoding on
the writer's threads overlaps rendering.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.euroc_writer import EurocWriter, depth_to_millimetres
from uavcal_jax.data.sequence import CameraCalibration
from uavcal_jax.data.targets import TargetLabels, TargetTracks
from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim import motion_blur, render, scene, sensor
from uavcal_jax.sim.config import CAMERAS, SimConfig, sensor_model
from uavcal_jax.sim.follow_targets import follow_request
from uavcal_jax.sim.scene_build import make_scene
from uavcal_jax.sim.sensor import SensorModel
from uavcal_jax.sim.target_boxes import target_boxes

__all__ = ["CameraEffects", "body_poses", "camera_effects", "frame_times",
           "make_frame_renderer", "render_frames", "sub_exposure_poses"]


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


@dataclass(frozen=True)
class CameraEffects:
    """What happens between the rendered radiance and the written 8-bit frame (static: one
    compiled renderer per value).

    Attributes:
        sensor: exposure x gain mapping and its constants, or ``None`` for the ideal camera
            (``round(255 L)``).
        noise: shot and read noise (with ``sensor``).
        blur_samples: sub-exposures averaged for motion blur (1 = none).
    """

    sensor: SensorModel | None = None
    noise: bool = False
    blur_samples: int = 1


def camera_effects(config: SimConfig) -> CameraEffects:
    """The :class:`CameraEffects` of a configuration (none with ``ideal_camera``)."""
    if config.ideal_camera:
        return CameraEffects()
    return CameraEffects(sensor=sensor_model(config), noise=bool(config.sensor_noise),
                         blur_samples=int(config.blur_samples))


@functools.lru_cache(maxsize=8)
def make_frame_renderer(color: str, n_targets: int, effects: CameraEffects = CameraEffects()):
    """A jitted ``fn(scene, bundle0, bundle1, cam0, cam1, T_WC0 (B,4,4), T_WC1 (B,4,4),
    t (B,), T_CmCs0 (B,S,4,4), T_CmCs1 (B,S,4,4), frame (B,) int32, key)`` returning per
    camera ``(image uint8 (B,H,W[,3]), depth uint16 mm (B,H,W), boxes (B,n,4), visible (B,n))``.

    ``bundleN`` is :func:`uavcal_jax.sim.render.ray_bundle` of camera N and ``camN`` its
    lens (arguments, not baked-in constants). Frames are rendered at mid-exposure by
    :func:`~uavcal_jax.sim.render.render_batch`; with ``effects`` the radiance is blurred over
    the sub-exposure poses ``T_CmCsN`` (:func:`uavcal_jax.sim.motion_blur.blur_image`) and
    exposed by :func:`uavcal_jax.sim.sensor.sensor_image` with the noise key
    ``fold_in(fold_in(key, frame), camera)``, so a frame's noise does not depend on the batch
    it falls in. Quantisation happens on the device, so only uint8 / uint16 images are
    transferred. Cached: simulations in one process share the compiled function."""

    def expose(image, depth, bundle, cam, rel, keys):
        if effects.sensor is None:
            return sensor.ideal_image(image)
        if effects.blur_samples > 1:
            image = jax.lax.map(lambda a: motion_blur.blur_image(
                a[0], a[1], bundle.rx, bundle.ry, a[2], cam), (image, depth, rel))
        if effects.noise:
            return jax.vmap(lambda img, k: sensor.sensor_image(img, k, effects.sensor))(
                image, keys)
        mean = effects.sensor.mean_dn(image)
        return jnp.clip(jnp.round(mean), 0, sensor.DN_MAX).astype(jnp.uint8)

    def one_camera(scn, bundle, cam, T_WC, t, rel, keys):
        out = render.render_batch(scn, None, T_WC, t, color=color, rays=bundle)
        img8 = expose(out.image, out.depth, bundle, cam, rel, keys)
        depth_mm = depth_to_millimetres(out.depth, jnp)
        boxes, visible = target_boxes(out.object_id, n_targets)
        return img8, depth_mm, boxes, visible

    def batch(scn, bundle0, bundle1, cam0, cam1, T0, T1, t, rel0, rel1, frame, key):
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(frame)
        keys0, keys1 = (jax.vmap(lambda k, c=c: jax.random.fold_in(k, c))(keys) for c in (0, 1))
        return (one_camera(scn, bundle0, cam0, T0, t, rel0, keys0),
                one_camera(scn, bundle1, cam1, T1, t, rel1, keys1))

    return jax.jit(batch)


def _target_info(scn, t_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Class ids (n,), world positions (N, n, 3) at the frame times, and class names."""
    poses = np.asarray(jax.vmap(lambda t: scene.target_poses(scn, t))(jnp.asarray(t_rel)))
    class_id = np.asarray(scn.targets.class_id, dtype=np.int64).reshape(-1)
    return class_id, poses[..., :3, 3].astype(np.float64), scene.target_class_names(scn)


def sub_exposure_poses(traj, cam_t_ns: np.ndarray, T_BS: np.ndarray, exposure_s: float,
                       samples: int, t_span_ns: tuple[int, int]) -> np.ndarray:
    """(N, S, 4, 4) float64 ``T_CmCs``: camera ``T_BS``'s pose at the ``S`` sub-exposure
    midpoints of each frame (:func:`~uavcal_jax.sim.motion_blur.exposure_times`, clamped to
    ``t_span_ns``) relative to its mid-exposure pose, along the trajectory."""
    t_sub = motion_blur.exposure_times(cam_t_ns, exposure_s, samples, *t_span_ns)
    T_WC_sub = body_poses(traj, t_sub.reshape(-1)).reshape(*t_sub.shape, 4, 4) @ T_BS
    return motion_blur.relative_poses(body_poses(traj, cam_t_ns) @ T_BS, T_WC_sub)


def render_frames(config: SimConfig, traj, imu_t_ns: np.ndarray,
                  calibs: dict[str, CameraCalibration], scene_seed: int, writer: EurocWriter,
                  show_progress: bool, camera_seed: int = 0, *,
                  cam_t_ns: np.ndarray | None = None
                  ) -> tuple[dict[str, Any], dict[str, float]]:
    """Render both cameras at the frame times and queue frames, depth and labels to
    ``writer``; ``camera_seed`` seeds the sensor noise. Returns the scene/counts description
    (and the camera effects applied) and the stage timings (``compile``, ``render``,
    ``write_wait``).

    ``cam_t_ns``: (N,) int64 increasing frame timestamps within ``imu_t_ns``' span (a real
    recording's camera clock, :mod:`uavcal_jax.sim.hybrid`); default
    :func:`frame_times` of ``imu_t_ns``."""

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    if cam_t_ns is None:
        cam_t_ns = frame_times(imu_t_ns, config)
    cam_t_ns = np.asarray(cam_t_ns, dtype=np.int64)
    if cam_t_ns.ndim != 1 or cam_t_ns.size == 0 or np.any(np.diff(cam_t_ns) <= 0) \
            or cam_t_ns[0] < imu_t_ns[0] or cam_t_ns[-1] > imu_t_ns[-1]:
        raise ValueError("cam_t_ns must be increasing frame times within the IMU's span")
    n = cam_t_ns.shape[0]
    t_rel = (cam_t_ns - int(imu_t_ns[0])) * 1e-9  # scene clock: seconds since the first sample
    T_WB = body_poses(traj, cam_t_ns)
    T_WC = {name: T_WB @ calibs[name].T_BS for name in CAMERAS}
    effects = camera_effects(config)
    S = effects.blur_samples
    span = (int(imu_t_ns[0]), int(imu_t_ns[-1]))
    T_CmCs = {name: (sub_exposure_poses(traj, cam_t_ns, calibs[name].T_BS,
                                        effects.sensor.exposure_s, S, span) if S > 1
                     else np.broadcast_to(np.eye(4), (n, 1, 4, 4))) for name in CAMERAS}

    lo, hi = traj.bounds()
    path_t = traj.times(10.0)
    path = traj.position(path_t)  # obstacles and targets keep clear of the path
    optical_axis = traj.rotation_matrix(path_t) @ calibs[CAMERAS[0]].T_BS[:3, 2]
    scn = make_scene(lo, hi, scene_seed, path_points=path, view_directions=optical_axis,
                     follow=_follow(config, traj, calibs, imu_t_ns))
    class_id, positions, class_names = _target_info(scn, t_rel)
    n_targets = int(class_id.shape[0])
    lenses = [camera_model.from_calibration(calibs[name]) for name in CAMERAS]
    bundles = [jax.tree_util.tree_map(jnp.asarray, render.ray_bundle(lens)) for lens in lenses]
    lenses = [lens.astype(jnp.float32) for lens in lenses]
    key = jax.random.PRNGKey(camera_seed)
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
        return (*lenses, *(jnp.asarray(T_WC[name][idx], dtype) for name in CAMERAS),
                jnp.asarray(t_rel[idx], dtype),
                *(jnp.asarray(T_CmCs[name][idx], dtype) for name in CAMERAS),
                jnp.asarray(idx, jnp.int32), key)

    fn = make_frame_renderer(config.color, n_targets, effects)
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
        writer.write_targets(_labels(rows, class_names, _target_tracks(scn, cam_t_ns, t_rel)))
    write_wait += time.perf_counter() - tw
    timings["render"] = render_wait
    timings["write_wait"] = write_wait
    info = {
        "counts": {"frames": n, "target_rows": len(rows) if config.targets else 0},
        "camera_model": {
            "ideal": effects.sensor is None,
            "sensor": None if effects.sensor is None else effects.sensor.to_dict(),
            "noise": effects.noise, "blur_samples": effects.blur_samples,
            "blur": "mid-exposure render warped to each sub-exposure pose by its depth"
                    if effects.blur_samples > 1 else None,
            "noise_seed": camera_seed if effects.noise else None},
        "scene": {"seed": scene_seed, "n_targets": n_targets,
                  "target_class_ids": class_id.tolist(), "class_names": list(class_names),
                  "room_lo": np.asarray(scn.room_lo).tolist(),
                  "room_hi": np.asarray(scn.room_hi).tolist(),
                  "flight_bounds_lo": np.asarray(lo).tolist(),
                  "flight_bounds_hi": np.asarray(hi).tolist()},
    }
    return info, timings


def _follow(config: SimConfig, traj, calibs, imu_t_ns: np.ndarray):
    """The follow targets' :class:`~uavcal_jax.sim.follow_targets.FollowRequest` (cam0 over
    the IMU's span, scene time 0 at its first sample), or ``None``."""
    cam = calibs[CAMERAS[0]]
    return follow_request(traj, cam.T_BS, cam.intrinsics, cam.resolution, int(imu_t_ns[0]),
                          int(imu_t_ns[-1]), config.follow_targets)


def _target_tracks(scn, cam_t_ns: np.ndarray, t_rel: np.ndarray) -> TargetTracks:
    """Every target's world state at every frame time (``target0/track.csv``)."""
    pos, yaw, vel = (np.asarray(a, dtype=np.float64) for a in jax.vmap(
        lambda t: scene.target_states(scn, t))(jnp.asarray(t_rel, jnp.float32)))
    class_id = np.asarray(scn.targets.class_id, dtype=np.int64).reshape(-1)
    return TargetTracks(t_ns=np.asarray(cam_t_ns, dtype=np.int64),
                        track_id=np.arange(class_id.shape[0], dtype=np.int64),
                        class_id=class_id, position=pos, yaw=yaw, velocity=vel)


def _labels(rows: list[tuple], class_names: tuple[str, ...],
            tracks: TargetTracks | None = None) -> TargetLabels:
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
        tracks=tracks,
    )
