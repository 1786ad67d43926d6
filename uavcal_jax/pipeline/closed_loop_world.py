"""The simulated world of a closed-loop flight (:mod:`uavcal_jax.pipeline.closed_loop`): the
scripted car's scene, the drone's start behind it, the IMU stream the drone writes as it flies,
and the renderer of the stereo pair and the left depth image from the drone's true pose.

Frames: ``Q`` the quadrotor (x forward, z up, what the drone model flies), ``B`` the IMU (the
body frame of the VIO and of the camera extrinsics; EuRoC's mounting ``R_QB``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.euroc_rig import euroc_imu_mounting
from uavcal_jax.data.sequence import CameraCalibration, ImuData
from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.sim import render, scene
from uavcal_jax.sim.config import CAMERAS, SimConfig, camera_calibrations, sensor_model, stage_seeds
from uavcal_jax.sim.drone_model import DroneState, hover_state, imu_samples
from uavcal_jax.sim.frames import CameraEffects, make_frame_renderer
from uavcal_jax.sim.ground_target import GroundPath, ground_track, scene_with_track
from uavcal_jax.sim.imu_synth import imu_noise
from uavcal_jax.track import FollowConfig

__all__ = ["World", "build_world"]


@dataclasses.dataclass
class World:
    """One flight's world (:func:`build_world`).

    Attributes:
        scene: the rendered scene with the car; target_class: (n,) its targets' class ids.
        start: the drone's hover state at the start.
        calibrations: cam0 and cam1 (:data:`~uavcal_jax.sim.config.CAMERAS`).
        imu: the IMU stream (filled by :meth:`write_imu` as the drone flies; a VIO keeps a
            reference to its arrays).
        lead: IMU samples of hover before the first frame; rate_ratio: IMU samples per frame;
            n_frames: frames of the flight.
        R_QB: (3, 3) the IMU's mounting in the quadrotor.
    """

    scene: scene.Scene
    target_class: np.ndarray
    start: DroneState
    calibrations: dict[str, CameraCalibration]
    imu: ImuData
    lead: int
    rate_ratio: int
    n_frames: int
    R_QB: np.ndarray
    noise: dict | None
    dt_imu: float
    _render: object
    _views: tuple

    def write_imu(self, flight, k0: int) -> None:
        """Samples ``k0 .. k0 + n - 1`` from a flight that started at sample ``k0``, and the
        accelerometer of sample ``k0 + n`` (known from the state alone)."""
        imu, R_QB = self.imu, self.R_QB
        gyro_q, accel_q = imu_samples(flight, self.dt_imu)
        n = gyro_q.shape[0]
        end_accel = R_QB.T @ (flight.R_WQ[-1].T @ (flight.a[-1] - np.asarray(GRAVITY_W)))
        imu.gyro[k0:k0 + n] = gyro_q @ R_QB  # R_QB^T g, row-wise
        imu.accel[k0:k0 + n] = accel_q @ R_QB
        imu.accel[k0 + n] = end_accel
        imu.gyro[k0 + n] = imu.gyro[k0 + n - 1] if n else 0.0  # finite stand-in, replaced
        if self.noise is not None:
            sl = slice(k0, k0 + n + 1)
            imu.gyro[sl] += self.noise["bias_gyro"][sl] + self.noise["white_gyro"][sl]
            imu.accel[sl] += self.noise["bias_accel"][sl] + self.noise["white_accel"][sl]

    def render(self, T_WB: np.ndarray, t_scene: float, j: int):
        """Frame ``j`` from the body pose ``T_WB`` (4, 4) at scene time ``t_scene`` s:
        ``(left, right, depth, boxes, visible)``: the uint8 pair (H, W), the left z-depth
        (H, W) metres, and the targets' boxes (n, 4) with their visible pixels (n,)."""
        bundles, lenses32, T_BS, key = self._views
        eye = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (1, 1, 4, 4))
        T0, T1 = (jnp.asarray((T_WB @ T)[None], jnp.float32) for T in T_BS)
        out = self._render(self.scene, bundles[0], bundles[1], *lenses32, T0, T1,
                           jnp.asarray([t_scene], jnp.float32), eye, eye,
                           jnp.asarray([j], jnp.int32), key)
        (img0, dep0, boxes0, vis0), (img1, _, _, _) = jax.device_get(out)
        return img0[0], img1[0], dep0[0].astype(np.float32) * 1e-3, boxes0[0], vis0[0]

    def target_position(self, t_scene: float) -> np.ndarray:
        """(3,) the car's true centre at scene time ``t_scene``."""
        return np.asarray(scene.target_states(self.scene, t_scene)[0], np.float64)[0]


def build_world(sim: SimConfig, path: GroundPath, follow: FollowConfig, lead_s: float,
                frames_duration: float, start_offset=(0.0, 0.0, 0.0)) -> World:
    """The car's scene along ``path``, the drone hovering ``follow.distance`` behind it and
    ``follow.height`` above (plus ``start_offset`` (3,) metres, world), an IMU stream for
    ``lead_s`` seconds of hover plus ``frames_duration`` seconds of frames (rates, resolution,
    pitch, seed and IMU noise from ``sim``; no motion blur: the sub-exposure poses would be
    in the future)."""
    rate_ratio = int(round(sim.imu_rate_hz / sim.camera_rate_hz))
    dt_imu = 1.0 / sim.imu_rate_hz
    seeds = stage_seeds(sim.seed)
    n_frames = int(np.floor(frames_duration * sim.camera_rate_hz + 1e-9)) + 1
    lead = int(round(lead_s * sim.imu_rate_hz / rate_ratio)) * rate_ratio
    n_imu = lead + (n_frames - 1) * rate_ratio + 1
    track = ground_track(path, n_imu * dt_imu + 1.0)
    margin = follow.distance + 1.5
    flight_lo = np.array([*(track[:, :2].min(0) - margin), 0.0])
    flight_hi = np.array([*(track[:, :2].max(0) + margin), 0.8 + follow.height + 1.0])
    scn = scene_with_track(track, flight_lo, flight_hi, seeds["scene"])
    target_z = float(np.asarray(scn.targets.z)[0])
    start = hover_state(np.array([track[0, 0] - follow.distance, track[0, 1],
                                  target_z + follow.height]) + np.asarray(start_offset),
                        float(track[0, 2]))
    t_imu = np.arange(n_imu, dtype=np.int64) * int(round(1e9 * dt_imu))
    imu = ImuData(t_ns=t_imu, gyro=np.zeros((n_imu, 3)), accel=np.zeros((n_imu, 3)))
    noise = imu_noise(n_imu, dt_imu, EUROC_ADIS16448, seeds["imu"]) if sim.imu_noise else None
    calibs = camera_calibrations(sim)
    effects = CameraEffects(sensor=sensor_model(sim), noise=True, blur_samples=1)
    lenses = [camera_model.from_calibration(calibs[n]) for n in CAMERAS]
    views = ([jax.tree_util.tree_map(jnp.asarray, render.ray_bundle(lens)) for lens in lenses],
             [lens.astype(jnp.float32) for lens in lenses],
             [np.asarray(calibs[n].T_BS, np.float64) for n in CAMERAS],
             jax.random.PRNGKey(seeds["camera"]))
    return World(scn, np.asarray(scn.targets.class_id, np.int64), start, calibs, imu, lead,
                 rate_ratio, n_frames, euroc_imu_mounting(), noise, dt_imu,
                 make_frame_renderer("gray", scn.n_targets, effects), views)
