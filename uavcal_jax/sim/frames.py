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
timestamp. Options (``SimConfig``): vignetting (:mod:`uavcal_jax.sim.vignetting`) on the
radiance before the sensor; auto-exposure (:mod:`uavcal_jax.sim.auto_exposure`), each frame's
exposure and gain set from the earlier frames' metering (cam0's, low-resolution renders in a
first pass) and applied to both cameras, the blur following each frame's exposure; a rolling
shutter (``line_delay_s``), each row warped to its own pose like the blur's sub-exposures
(:mod:`uavcal_jax.sim.motion_blur`; the timestamp is the middle row's).

Frames are rendered in fixed-size batches by one jitted function (compiled once; the last
batch is padded); the next batch is dispatched before this one is written, so PNG encoding on
the writer's threads overlaps rendering.
"""

from __future__ import annotations

import dataclasses
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
from uavcal_jax.sim import auto_exposure, motion_blur, render, scene, sensor, vignetting
from uavcal_jax.sim.config import CAMERAS, SimConfig, auto_exposure_settings, sensor_model
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
        vignetting: exponent of the ``cos^p`` falloff (0 = none).
        auto_exposure: per-frame exposure and gain (the renderer's ``settings``) replace
            ``sensor``'s.
        line_delay_s: rolling shutter's delay between rows, seconds (0 = global shutter); the
            sub-exposure poses are then one per row.
    """

    sensor: SensorModel | None = None
    noise: bool = False
    blur_samples: int = 1
    vignetting: float = 0.0
    auto_exposure: bool = False
    line_delay_s: float = 0.0


def camera_effects(config: SimConfig) -> CameraEffects:
    """The :class:`CameraEffects` of a configuration (none with ``ideal_camera``)."""
    if config.ideal_camera:
        return CameraEffects()
    return CameraEffects(sensor=sensor_model(config), noise=bool(config.sensor_noise),
                         blur_samples=int(config.blur_samples),
                         vignetting=float(config.vignetting),
                         auto_exposure=bool(config.auto_exposure),
                         line_delay_s=float(config.line_delay_s))


@functools.lru_cache(maxsize=8)
def make_frame_renderer(color: str, n_targets: int, effects: CameraEffects = CameraEffects()):
    """A jitted ``fn(scene, bundle0, bundle1, cam0, cam1, T_WC0 (B,4,4), T_WC1 (B,4,4),
    t (B,), T_CmCs0 (B,S,4,4), T_CmCs1 (B,S,4,4), frame (B,) int32, key, settings=None)``
    returning per camera ``(image uint8 (B,H,W[,3]), depth uint16 mm (B,H,W), boxes (B,n,4),
    visible (B,n))``. With a rolling shutter ``T_CmCsN`` are (B,S,H,4,4), one pose per row;
    with auto-exposure ``settings`` is (B, 2): each frame's exposure (s) and gain.

    ``bundleN`` is :func:`uavcal_jax.sim.render.ray_bundle` of camera N and ``camN`` its
    lens (arguments, not baked-in constants). Frames are rendered at mid-exposure by
    :func:`~uavcal_jax.sim.render.render_batch`; with ``effects`` the radiance is blurred over
    the sub-exposure poses ``T_CmCsN`` (:func:`uavcal_jax.sim.motion_blur.blur_image`) and
    exposed by :func:`uavcal_jax.sim.sensor.sensor_image` with the noise key
    ``fold_in(fold_in(key, frame), camera)``, so a frame's noise does not depend on the batch
    it falls in. Quantisation happens on the device, so only uint8 / uint16 images are
    transferred. Cached: simulations in one process share the compiled function."""

    def expose(image, depth, bundle, cam, rel, keys, settings):
        if effects.sensor is None:
            return sensor.ideal_image(image)
        if effects.blur_samples > 1 or effects.line_delay_s > 0:
            image = jax.lax.map(lambda a: motion_blur.blur_image(
                a[0], a[1], bundle.rx, bundle.ry, a[2], cam), (image, depth, rel))
        if effects.vignetting:
            v = vignetting.falloff(bundle.rx, bundle.ry, effects.vignetting).reshape(
                image.shape[1:3])
            image = image * (v[..., None] if image.ndim == 4 else v)
        if effects.auto_exposure:
            def one_frame(img, k, s):
                model = dataclasses.replace(effects.sensor, exposure_s=s[0], gain=s[1])
                if effects.noise:
                    return sensor.sensor_image(img, k, model)
                return jnp.clip(jnp.round(model.mean_dn(img)), 0, sensor.DN_MAX).astype(
                    jnp.uint8)
            return jax.vmap(one_frame)(image, keys, settings)
        if effects.noise:
            return jax.vmap(lambda img, k: sensor.sensor_image(img, k, effects.sensor))(
                image, keys)
        mean = effects.sensor.mean_dn(image)
        return jnp.clip(jnp.round(mean), 0, sensor.DN_MAX).astype(jnp.uint8)

    def one_camera(scn, bundle, cam, T_WC, t, rel, keys, settings):
        out = render.render_batch(scn, None, T_WC, t, color=color, rays=bundle)
        img8 = expose(out.image, out.depth, bundle, cam, rel, keys, settings)
        depth_mm = depth_to_millimetres(out.depth, jnp)
        boxes, visible = target_boxes(out.object_id, n_targets)
        return img8, depth_mm, boxes, visible

    def batch(scn, bundle0, bundle1, cam0, cam1, T0, T1, t, rel0, rel1, frame, key,
              settings=None):
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(frame)
        keys0, keys1 = (jax.vmap(lambda k, c=c: jax.random.fold_in(k, c))(keys) for c in (0, 1))
        return (one_camera(scn, bundle0, cam0, T0, t, rel0, keys0, settings),
                one_camera(scn, bundle1, cam1, T1, t, rel1, keys1, settings))

    return jax.jit(batch)


def _target_info(scn, t_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Class ids (n,), world positions (N, n, 3) at the frame times, and class names."""
    poses = np.asarray(jax.vmap(lambda t: scene.target_poses(scn, t))(jnp.asarray(t_rel)))
    class_id = np.asarray(scn.targets.class_id, dtype=np.int64).reshape(-1)
    return class_id, poses[..., :3, 3].astype(np.float64), scene.target_class_names(scn)


def sub_exposure_poses(traj, cam_t_ns: np.ndarray, T_BS: np.ndarray,
                       exposure_s: float | np.ndarray, samples: int,
                       t_span_ns: tuple[int, int], line_delay_s: float = 0.0,
                       rows: int = 1) -> np.ndarray:
    """(N, S, 4, 4) float64 ``T_CmCs``: camera ``T_BS``'s pose at the ``S`` sub-exposure
    midpoints of each frame (:func:`~uavcal_jax.sim.motion_blur.exposure_times`, exposure in
    seconds, one or (N,); clamped to ``t_span_ns``) relative to its mid-exposure pose, along
    the trajectory. With a rolling shutter (``line_delay_s > 0``) (N, S, rows, 4, 4): each
    row's own (:func:`~uavcal_jax.sim.motion_blur.row_times`)."""
    t_sub = motion_blur.exposure_times(cam_t_ns, exposure_s, samples, *t_span_ns)
    if line_delay_s > 0:
        t_sub = motion_blur.row_times(t_sub, rows, line_delay_s, *t_span_ns)
    T_WC_sub = body_poses(traj, t_sub.reshape(-1)).reshape(*t_sub.shape, 4, 4) @ T_BS
    n = t_sub.shape[0]
    return motion_blur.relative_poses(body_poses(traj, cam_t_ns) @ T_BS,
                                      T_WC_sub.reshape(n, -1, 4, 4)).reshape(T_WC_sub.shape)


def _metering(scn, lens: camera_model.PinholeRadtan, T_WC: np.ndarray, t_rel: np.ndarray,
              color: str, vignetting_exponent: float, batch: int) -> np.ndarray:
    """(N, h, w[, 3]) the auto-exposure's metering images: radiance rendered at
    :data:`~uavcal_jax.sim.auto_exposure.METERING_SCALE` of ``lens``'s size at the frames'
    poses ``T_WC`` (N, 4, 4), vignetted."""
    small = lens.scaled(auto_exposure.METERING_SCALE)
    bundle = jax.tree_util.tree_map(jnp.asarray, render.ray_bundle(small))
    v = np.asarray(vignetting.falloff(bundle.rx, bundle.ry, vignetting_exponent)).reshape(
        small.height, small.width)
    out = []
    for k in range(0, T_WC.shape[0], batch):
        img = render.render_batch(scn, None, jnp.asarray(T_WC[k:k + batch], jnp.float32),
                                  jnp.asarray(t_rel[k:k + batch], jnp.float32), color=color,
                                  rays=bundle).image
        out.append(np.asarray(img))
    image = np.concatenate(out)
    return image * (v[..., None] if image.ndim == 4 else v)


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

    S = effects.blur_samples
    span = (int(imu_t_ns[0]), int(imu_t_ns[-1]))
    settings = None  # (N, 2) per-frame exposure (s) and gain with auto-exposure
    exposure = None if effects.sensor is None else effects.sensor.exposure_s
    if effects.auto_exposure:
        metering = _metering(scn, camera_model.from_calibration(calibs[CAMERAS[0]]),
                             T_WC[CAMERAS[0]], t_rel, config.color, effects.vignetting,
                             config.batch_size)
        exposure, gain = auto_exposure.exposure_schedule(
            metering, np.diff(cam_t_ns) * 1e-9, effects.sensor, auto_exposure_settings(config))
        settings = np.stack([exposure, gain], axis=1)
    image_rows = calibs[CAMERAS[0]].resolution[1]

    def rel_poses(name, idx):
        """Sub-exposure (and row) poses of frames ``idx``."""
        e = exposure if np.ndim(exposure) == 0 else exposure[idx]
        return sub_exposure_poses(traj, cam_t_ns[idx], calibs[name].T_BS, e, S, span,
                                  effects.line_delay_s, image_rows)

    # global shutter: all frames' poses at once; rolling: a batch's at a time (one per row)
    T_CmCs = {name: (rel_poses(name, np.arange(n)) if S > 1
                     else np.broadcast_to(np.eye(4), (n, 1, 4, 4))) for name in CAMERAS} \
        if effects.line_delay_s == 0 else None

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
        rel = [T_CmCs[name][idx] if T_CmCs is not None else rel_poses(name, idx)
               for name in CAMERAS]
        return (*lenses, *(jnp.asarray(T_WC[name][idx], dtype) for name in CAMERAS),
                jnp.asarray(t_rel[idx], dtype), *(jnp.asarray(r, dtype) for r in rel),
                jnp.asarray(idx, jnp.int32), key,
                None if settings is None else jnp.asarray(settings[idx], dtype))

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
            "vignetting": effects.vignetting, "line_delay_s": effects.line_delay_s,
            "auto_exposure": None if settings is None else {
                "settings": dataclasses.asdict(auto_exposure_settings(config)),
                "exposure_ms": np.round(settings[:, 0] * 1e3, 4).tolist(),
                "gain": np.round(settings[:, 1], 4).tolist()},
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
