"""What a simulated recording is: :class:`SimConfig`, and the calibration and seeds it implies.

A :class:`SimConfig` holds every choice that changes the output (flight, duration, frame size,
colour, rates, the camera's exposure, gain, noise and motion blur, seed, which streams, an
optional constant IMU offset) and two
that only change the speed (render batch, PNG threads). Its field defaults are the defaults of
``uavcal simulate`` and of the benchmarks, which read them from here.
:func:`camera_calibrations` and :func:`stage_seeds` resolve a configuration into EuRoC's two
cameras at its resolution and rate, and the seeds of the flight, IMU-noise, scene and
camera-noise stages; :func:`sensor_model` into the photometric settings of
:mod:`uavcal_jax.sim.sensor`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc_rig import (
    EUROC_IMU_RATE_HZ,
    EUROC_RATE_HZ,
    EUROC_RESOLUTION,
    euroc_calibration,
)
from uavcal_jax.data.sequence import CameraCalibration
from uavcal_jax.sim import auto_exposure as ae
from uavcal_jax.sim.mounting import pitched_rig
from uavcal_jax.sim.sensor import SensorModel
from uavcal_jax.sim.vignetting import EUROC_VIGNETTING

__all__ = [
    "BODY_FRAMES",
    "CAMERAS",
    "COLORS",
    "EUROC_CAMERA_PRESET",
    "EUROC_IMU_REALISM",
    "IDEAL_IMU",
    "IDEAL_SENSORS",
    "IMU_ERRORS",
    "LOW_RESOLUTION",
    "SimConfig",
    "auto_exposure_settings",
    "camera_calibrations",
    "imu_rotation",
    "scale_calibration",
    "sensor_model",
    "stage_seeds",
]

#: Simulated camera names; cam N uses EuRoC's cam N calibration.
CAMERAS = ("cam0", "cam1")
#: Colour modes of the frames: 8-bit gray (like EuRoC; the default) or RGB.
COLORS = ("gray", "rgb")
#: Body-frame conventions of a trajectory file (:attr:`SimConfig.body_frame`): EuRoC's IMU
#: frame (x up, z forward) or a quadrotor frame x forward, y left, z up.
BODY_FRAMES = ("euroc", "flu")
#: The fast render size (width, height): EuRoC's 752x480 halved, a quarter of its pixels (the
#: detector's input is 384x256 anyway). The cached training sets, the demo and the long-flight
#: and closed-loop studies render at it.
LOW_RESOLUTION: tuple[int, int] = (EUROC_RESOLUTION[0] // 2, EUROC_RESOLUTION[1] // 2)
#: Stages with their own random stream, in :func:`stage_seeds`' order.
STAGES = ("flight", "imu", "scene", "camera")
#: EuRoC's VI-sensor camera effects, on by default: its MT9V034s run auto-exposure and are
#: global shutter (``line_delay_s`` stays 0). The vignetting is measured on the static micro
#: slice (``python experiments/camera_fit.py ../shared/data/euroc_v101_micro``, which also
#: checks ``sim.sensor``'s noise constants); the AE's target is that slice's mean, its time
#: constant typical (a static slice cannot show it): :mod:`uavcal_jax.sim.auto_exposure`.
EUROC_CAMERA_PRESET: dict[str, Any] = {"auto_exposure": True, "vignetting": EUROC_VIGNETTING,
                                       "line_delay_s": 0.0}

#: The simulated IMU's errors beyond its noise (SimConfig fields).
IMU_ERRORS = ("imu_vibration", "imu_scale", "imu_misalignment", "imu_g_sensitivity",
              "imu_time_offset")
#: The IMU error settings given as number lists, and their lengths.
_IMU_ERROR_COUNTS = {"imu_scale": 6, "imu_misalignment": 6, "imu_g_sensitivity": 9}
_DEG = float(np.pi / 180.0)
_G = 9.81
#: EuRoC-like IMU errors, on by default. The vibration is V1_01's measured spectrum; the rest
#: are ADIS16448-class magnitudes (its data sheet: sensitivity tolerance about 1 %, axis-to-axis
#: misalignment 0.05 degrees for the gyros and 0.2 degrees for the accelerometers,
#: linear-acceleration effect on the gyro bias about 0.01 degree/s per g), one fixed draw of
#: signs and sizes so that runs compare. The time offset stays 0: EuRoC's VI-sensor triggers
#: its cameras on the IMU's clock (hardware sync); a few milliseconds is typical of
#: unsynchronised rigs.
EUROC_IMU_REALISM: dict = {
    "imu_vibration": 1.0,
    "imu_scale": (3e-3, -2e-3, 4e-3, -2.5e-3, 1.5e-3, 3.5e-3),
    "imu_misalignment": tuple(v * _DEG for v in (0.04, -0.03, 0.05, 0.15, -0.2, 0.1)),
    "imu_g_sensitivity": tuple(v * _DEG / _G for v in (0.01, -0.004, 0.006, 0.003, 0.009,
                                                       -0.005, -0.007, 0.002, 0.01)),
    "imu_time_offset": 0.0,
}


#: Every realism effect above off: an ideal camera response (fixed exposure and gain, no
#: vignetting) and an IMU with only its white noise and bias random walk, as the simulator was
#: before issue 42 (``dataclasses.replace(config, **IDEAL_SENSORS)``, ``sim_realism.py --preset
#: ideal``). For studies that isolate one effect; the defaults are EuRoC's rig.
IDEAL_SENSORS: dict[str, Any] = {"auto_exposure": False, "vignetting": 0.0, "line_delay_s": 0.0,
                                 "imu_vibration": 0.0, "imu_scale": None,
                                 "imu_misalignment": None, "imu_g_sensitivity": None,
                                 "imu_time_offset": 0.0}
#: The IMU's errors beyond its data-sheet noise off (the cameras' realism kept): for studies
#: of a constant offset's recovery to 1e-4, which the vibration (V1_01's 0.05 rad/s and 1.4
#: m/s^2 RMS: its broadband part moves a 4 s mean by about 1e-3 rad/s) and the errors varying
#: with the motion (scale, misalignment, g-sensitivity) would blur.
IDEAL_IMU: dict[str, Any] = {name: IDEAL_SENSORS[name] for name in IMU_ERRORS}


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated recording.

    Attributes:
        trajectory: TUM trajectory file to fly (``t tx ty tz qx qy qz qw``, t in seconds), or
            ``None`` for a procedural flight (hover, turns, climbs, straight legs) from ``seed``.
        start: seconds after the trajectory file's first timestamp where the recording starts
            (ignored for procedural flights). Output timestamps stay on the file's clock.
        duration: seconds of flight to record.
        body_frame: the body convention of the trajectory file's orientations: ``"euroc"``
            (EuRoC's IMU frame, x up and z forward; the file's frame is the IMU frame) or
            ``"flu"`` (x forward, y left, z up, as UZH-FPV and most motion-capture rigs):
            EuRoC's IMU is then mounted on it as on EuRoC's MAV
            (:func:`uavcal_jax.sim.simulate.mount_imu` with
            :func:`~uavcal_jax.data.euroc_rig.euroc_imu_mounting`), as procedural flights
            (always built x forward, z up) are. Ignored for procedural flights.
        camera_pitch_deg: the stereo rig's pitch below the quadrotor's forward axis, degrees
            (0 looks forward, 90 straight down): both cameras are turned together about the
            body's lateral axis (:func:`uavcal_jax.sim.mounting.pitched_rig`) and their
            ``T_BS`` (written to ``sensor.yaml``) are the turned ones. ``None``: EuRoC's rig as
            it is, whose cam0 looks 19.8 degrees below forward (cam1 19.0) when the IMU sits
            as on EuRoC's MAV. For a ``"euroc"`` trajectory the quadrotor's axes are those of
            EuRoC's MAV mounting (:func:`uavcal_jax.data.euroc_rig.euroc_imu_mounting`).
        imu_rotation_deg: ``None``, or a rotation vector (3 numbers, degrees) that turns the
            IMU on the airframe: the recording's body frame is the turned IMU's, ``R_BI =
            exp(imu_rotation_deg)`` in the frame it had (:func:`imu_rotation`). The motion,
            the cameras' world poses and so the frames are unchanged; the IMU's samples, the
            ground truth's orientations and the cameras' ``T_BS`` are expressed in the turned
            frame. Other drones hold their IMU in other orientations (gravity on z rather than
            EuRoC's x): this makes such a recording from any flight.
        rotor_drag: a procedural flight's rotor drag coefficient per unit mass, 1/s
            (:class:`uavcal_jax.sim.flights.FlightConfig`): the thrust axis tilts to
            balance it and the accelerometer reads ``-d v`` in the rotor plane. 0: the
            thrust exactly along ``a + g e_z``. Ignored for a trajectory file (its
            orientations are given).
        thrust_tilt_deg: ``None``, or a procedural flight's thrust axis tilted in the body
            frame about body x then y, degrees (the body leans to carry the thrust on it).
            Ignored for a trajectory file.
        resolution: ``(width, height)`` of the frames; other than EuRoC's 752x480, the EuRoC
            intrinsics are scaled to keep the field of view.
        color: ``"gray"`` (8-bit single channel, like EuRoC) or ``"rgb"``.
        seed: seeds the flight, the IMU noise and biases, and the scene.
        imu_noise: add EuRoC's ADIS16448 noise, bias random walk and turn-on biases; when false
            the IMU is exact (biases zero). ``imu0/sensor.yaml`` states EuRoC's noise model in
            both cases.
        imu_offset: ``None`` (no offset) or 6 finite numbers, gyro rad/s xyz then accel m/s^2
            xyz: a constant error added (:func:`uavcal_jax.imu.offset.add_offset`) to the
            written IMU after its noise and biases, i.e. a miscalibrated sensor. The ground
            truth's bias columns stay the IMU's true biases (without the offset), so
            ``remove_offset`` with this value gives back the recording without it.
        imu_vibration: rotor vibration, as a multiple of the amplitudes of EuRoC V1_01's
            measured spectrum (:data:`uavcal_jax.sim.imu_vibration.EUROC_V101_VIBRATION`:
            humps at 17.2, 27.3, 55.4, 72.7, 93.6 and 96.9 Hz and a broadband floor, per IMU
            axis, gyro rad/s and accel m/s^2); 0 is none, 1 (the default) is V1_01's (its band
            power above 15 Hz within 5 % per axis). Added to the motion
            before the intrinsics below (:mod:`uavcal_jax.sim.imu_synth`), with or without
            ``imu_noise``; the ground truth is the motion without it.
        imu_rest_vibration: with ``imu_vibration`` and a recorded ``trajectory``, where it
            rests (no measurable motion for a second: standing before take-off, rotors
            idling; a planned flight's still hovers are in flight) the spectrum is
            V1_01's standing one instead
            (:data:`uavcal_jax.sim.imu_vibration.EUROC_V101_REST_VIBRATION`: humps near 19 Hz,
            a third of the flight's accelerometer vibration), ramped over the rotors' spool-up
            (:func:`uavcal_jax.sim.imu_vibration.rest_weight`); false: the flight's spectrum
            throughout, as before.
        imu_scale: ``None`` (none) or 6 fractions, gyro x, y, z then accel x, y, z (IMU frame):
            each axis reads ``(1 + scale)`` times its input (1e-3 = 1000 ppm). The defaults of
            this and the next two are :data:`EUROC_IMU_REALISM`'s. With
            ``imu_misalignment`` and ``imu_g_sensitivity`` this is OpenVINS's "kalibr" IMU
            model (:class:`uavcal_jax.sim.imu_synth.ImuIntrinsics`: ``T_w``, ``T_a``, ``T_g``;
            OpenVINS estimates ``D = T^-1``).
        imu_misalignment: ``None`` or 6 small angles (rad), the strictly lower triangles of
            ``T_w`` (gyro ``[1,0], [2,0], [2,1]``) then ``T_a`` (accel, likewise): the
            axes' non-orthogonality.
        imu_g_sensitivity: ``None`` or 9 numbers, ``T_g`` row-major, rad/s per m/s^2: the
            gyro reads ``T_g a`` more for a specific force ``a`` (IMU frame, m/s^2).
        imu_time_offset: seconds, Kalibr's ``timeshift_cam_imu`` (``t_imu = t_cam + shift``):
            the IMU sample stamped ``t`` measures the motion at camera/ground-truth time ``t -
            imu_time_offset`` (positive: the IMU's stamps run late). The frames and the ground
            truth stay on the camera clock; 0 (the default) is none.
        frames: render and write cam0/cam1 (and depth, targets); false writes only the IMU and
            the ground truth.
        depth: write depth0/depth1 with the frames.
        targets: write target0 labels with the frames.
        follow_targets: moving targets (car, person, alternating) to place on the floor where
            the left camera looks along the flight (:mod:`uavcal_jax.sim.follow_targets`):
            each moves, stops and turns, staying in cam0's view most of the time. They are
            track ids ``0 .. follow_targets - 1`` of the labels (the scene's other targets
            follow); their world tracks are in ``target0/track.csv``.
        camera_rate_hz: frame rate (EuRoC: 20 Hz).
        imu_rate_hz: IMU and ground-truth rate (EuRoC: 200 Hz).
        ideal_camera: write the renderer's noise-free, sharp image (``round(255 L)``) and
            ignore the four camera settings below; false (the default) images like EuRoC's
            MT9V034 (:mod:`uavcal_jax.sim.sensor`, :mod:`uavcal_jax.sim.motion_blur`).
        exposure_ms: exposure time, milliseconds. EuRoC's auto-exposure runs at about 1-10 ms
            indoors; 5 ms is the middle of that range, and with the sensor's calibrated scene
            illumination and gain 1 it gives V1_01's mean intensity.
        gain: analog gain (brightness and noise scale with it; 1 = V1_01's measured
            operating point).
        sensor_noise: shot noise, read noise (and the full-well clip) on the electrons.
        blur_samples: sub-exposures averaged for motion blur (1 = no blur); the camera's pose
            at each comes from the trajectory. Depth and target labels are at mid-exposure.
        vignetting: exponent ``p`` of the lens's ``cos(theta)^p`` falloff (0 = none; 4 = the
            cos^4 law; the default is EuRoC's, :data:`EUROC_CAMERA_PRESET`),
            :mod:`uavcal_jax.sim.vignetting`.
        auto_exposure: exposure and gain follow the scene's brightness frame by frame
            (:mod:`uavcal_jax.sim.auto_exposure`; ``exposure_ms`` and ``gain`` are the first
            frame's), metered on cam0 and shared by both cameras (on by default, as EuRoC's).
        ae_target_dn: the auto-exposure's target mean intensity, DN.
        ae_time_constant_s: the auto-exposure's time constant, seconds.
        line_delay_s: rolling shutter: row ``r`` is exposed ``line_delay_s`` after row
            ``r - 1`` (0 = global shutter, as EuRoC's); the frame's timestamp, depth and labels
            are the middle row's.
        batch_size: frames rendered per jitted call (speed/memory only, not the output).
        png_workers: threads encoding PNGs (speed only).
    """

    trajectory: str | None = None
    start: float = 0.0
    duration: float = 10.0
    body_frame: str = BODY_FRAMES[0]
    camera_pitch_deg: float | None = None
    imu_rotation_deg: tuple[float, float, float] | None = None
    rotor_drag: float = 0.0
    thrust_tilt_deg: tuple[float, float] | None = None
    resolution: tuple[int, int] = EUROC_RESOLUTION
    color: str = COLORS[0]
    seed: int = 0
    imu_noise: bool = True
    imu_offset: tuple[float, ...] | None = None
    imu_vibration: float = EUROC_IMU_REALISM["imu_vibration"]
    imu_rest_vibration: bool = True
    imu_scale: tuple[float, ...] | None = EUROC_IMU_REALISM["imu_scale"]
    imu_misalignment: tuple[float, ...] | None = EUROC_IMU_REALISM["imu_misalignment"]
    imu_g_sensitivity: tuple[float, ...] | None = EUROC_IMU_REALISM["imu_g_sensitivity"]
    imu_time_offset: float = EUROC_IMU_REALISM["imu_time_offset"]
    frames: bool = True
    depth: bool = True
    targets: bool = True
    follow_targets: int = 0
    camera_rate_hz: float = EUROC_RATE_HZ
    imu_rate_hz: float = EUROC_IMU_RATE_HZ
    ideal_camera: bool = False
    exposure_ms: float = 5.0
    gain: float = 1.0
    sensor_noise: bool = True
    blur_samples: int = 5
    vignetting: float = EUROC_CAMERA_PRESET["vignetting"]
    auto_exposure: bool = EUROC_CAMERA_PRESET["auto_exposure"]
    ae_target_dn: float = ae.AE_TARGET_DN
    ae_time_constant_s: float = ae.AE_TIME_CONSTANT_S
    line_delay_s: float = EUROC_CAMERA_PRESET["line_delay_s"]
    batch_size: int = 8
    png_workers: int = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
        for name in ("start", "duration", "camera_rate_hz", "imu_rate_hz", "exposure_ms", "gain",
                     "vignetting", "ae_target_dn", "ae_time_constant_s", "line_delay_s"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.trajectory is not None:
            object.__setattr__(self, "trajectory", os.fspath(self.trajectory))
        if self.camera_pitch_deg is not None:
            object.__setattr__(self, "camera_pitch_deg", float(self.camera_pitch_deg))
        if self.imu_rotation_deg is not None:
            object.__setattr__(self, "imu_rotation_deg",
                               tuple(float(v) for v in self.imu_rotation_deg))
        if self.thrust_tilt_deg is not None:
            object.__setattr__(self, "thrust_tilt_deg",
                               tuple(float(v) for v in self.thrust_tilt_deg))
        if self.imu_offset is not None:
            # a tuple of floats whatever sequence was given (hashable, JSON-ready, and equal
            # to the parsed command-line value); the count is checked by validate()
            object.__setattr__(self, "imu_offset", tuple(float(v) for v in self.imu_offset))
        for name in ("imu_vibration", "imu_time_offset"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in _IMU_ERROR_COUNTS:
            if getattr(self, name) is not None:
                object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))

    def validate(self) -> None:
        """Raise ``ValueError`` for values out of range (the file is checked by simulate)."""
        if self.color not in COLORS:
            raise ValueError(f"color must be one of {COLORS}, got {self.color!r}")
        if self.body_frame not in BODY_FRAMES:
            raise ValueError(f"body_frame must be one of {BODY_FRAMES}, got {self.body_frame!r}")
        if self.camera_pitch_deg is not None and not (
                np.isfinite(self.camera_pitch_deg) and -90.0 <= self.camera_pitch_deg <= 90.0):
            raise ValueError("camera_pitch_deg must be in [-90, 90] degrees (0 forward, 90 "
                             f"down), got {self.camera_pitch_deg}")
        if not 0 <= self.follow_targets <= 8:
            raise ValueError(f"follow_targets must be 0..8, got {self.follow_targets}")
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
        if not (np.isfinite(self.exposure_ms) and self.exposure_ms > 0):
            raise ValueError(f"exposure_ms must be positive, got {self.exposure_ms}")
        if self.exposure_ms * 1e-3 > 1.0 / self.camera_rate_hz:
            raise ValueError(f"exposure_ms {self.exposure_ms:g} is longer than the frame period")
        if not (np.isfinite(self.gain) and self.gain > 0):
            raise ValueError(f"gain must be positive, got {self.gain}")
        if self.blur_samples < 1:
            raise ValueError(f"blur_samples must be >= 1, got {self.blur_samples}")
        if not (np.isfinite(self.vignetting) and self.vignetting >= 0):
            raise ValueError(f"vignetting must be >= 0 (a cos^p exponent), got {self.vignetting}")
        if not (0 < self.ae_target_dn < 255 and self.ae_time_constant_s > 0):
            raise ValueError("ae_target_dn must be in (0, 255) DN and ae_time_constant_s > 0, "
                             f"got {self.ae_target_dn}, {self.ae_time_constant_s}")
        if not (np.isfinite(self.line_delay_s) and self.line_delay_s >= 0
                and self.line_delay_s * self.resolution[1] <= 1.0 / self.camera_rate_hz):
            raise ValueError("line_delay_s must be >= 0 and its readout (x rows) within the "
                             f"frame period, got {self.line_delay_s}")
        if self.imu_offset is not None and not (
                len(self.imu_offset) == 6 and np.all(np.isfinite(self.imu_offset))):
            raise ValueError("imu_offset must be 6 finite numbers (gyro rad/s xyz, accel m/s^2 "
                             f"xyz), got {self.imu_offset}")
        if not (np.isfinite(self.rotor_drag) and 0.0 <= self.rotor_drag <= 5.0):
            raise ValueError(f"rotor_drag must be in [0, 5] 1/s, got {self.rotor_drag}")
        if self.thrust_tilt_deg is not None and not (
                len(self.thrust_tilt_deg) == 2
                and np.all(np.abs(self.thrust_tilt_deg) <= 30.0)):
            raise ValueError("thrust_tilt_deg must be 2 angles within +-30 degrees, got "
                             f"{self.thrust_tilt_deg}")
        if self.imu_rotation_deg is not None and not (
                len(self.imu_rotation_deg) == 3 and np.all(np.isfinite(self.imu_rotation_deg))):
            raise ValueError("imu_rotation_deg must be 3 finite numbers (a rotation vector, "
                             f"degrees), got {self.imu_rotation_deg}")
        for name, count in _IMU_ERROR_COUNTS.items():
            value = getattr(self, name)
            if value is not None and not (len(value) == count and np.all(np.isfinite(value))):
                raise ValueError(f"{name} must be {count} finite numbers, got {value}")
        if not (np.isfinite(self.imu_vibration) and self.imu_vibration >= 0):
            raise ValueError(f"imu_vibration must be >= 0, got {self.imu_vibration}")
        if not (np.isfinite(self.imu_time_offset) and abs(self.imu_time_offset) < 1.0):
            raise ValueError(f"imu_time_offset must be under 1 s, got {self.imu_time_offset}")
        if self.batch_size < 1 or self.png_workers < 1:
            raise ValueError("batch_size and png_workers must be >= 1")

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON-ready values (``sim_config.json``'s ``config``)."""
        d = dataclasses.asdict(self)
        d["resolution"] = list(self.resolution)
        d["imu_offset"] = None if self.imu_offset is None else list(self.imu_offset)
        for name in _IMU_ERROR_COUNTS:
            d[name] = None if getattr(self, name) is None else list(getattr(self, name))
        d["imu_rotation_deg"] = (None if self.imu_rotation_deg is None
                                 else list(self.imu_rotation_deg))
        return d


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


def imu_rotation(config: SimConfig) -> np.ndarray:
    """(3, 3) ``R_BI``: the turned IMU's axes in the frame it had (``imu_rotation_deg``; the
    identity when ``None``)."""
    if config.imu_rotation_deg is None:
        return np.eye(3)
    return Rotation.from_rotvec(np.radians(config.imu_rotation_deg)).as_matrix()


def camera_calibrations(config: SimConfig) -> dict[str, CameraCalibration]:
    """EuRoC cam0/cam1 at the configured resolution and frame rate; with
    ``camera_pitch_deg`` their ``T_BS`` are the pitched rig's
    (:func:`uavcal_jax.sim.mounting.pitched_rig`), and with ``imu_rotation_deg`` expressed
    in the turned IMU's frame: the extrinsics the frames are rendered with and
    ``sensor.yaml`` states."""
    T_BS = pitched_rig([euroc_calibration(i).T_BS for i in range(len(CAMERAS))],
                       config.camera_pitch_deg)
    T_IB = np.eye(4)
    T_IB[:3, :3] = imu_rotation(config).T  # the rig in the turned IMU's frame
    T_BS = [T_IB @ T for T in T_BS]
    out = {}
    for i, name in enumerate(CAMERAS):
        calib = scale_calibration(euroc_calibration(i), config.resolution)
        out[name] = dataclasses.replace(calib, rate_hz=float(config.camera_rate_hz),
                                        T_BS=T_BS[i])
    return out


def sensor_model(config: SimConfig) -> SensorModel:
    """The configuration's photometric settings (exposure, gain; the sensor's constants)."""
    return SensorModel(exposure_s=config.exposure_ms * 1e-3, gain=config.gain)


def auto_exposure_settings(config: SimConfig) -> ae.AutoExposure:
    """The configuration's auto-exposure controller (target, time constant; the sensor's
    exposure and gain limits)."""
    return ae.AutoExposure(target_dn=config.ae_target_dn,
                           time_constant_s=config.ae_time_constant_s)


def stage_seeds(seed: int) -> dict[str, int]:
    """Independent seeds for the flight, the IMU noise, the scene and the camera noise, derived
    from ``seed`` (a SeedSequence's words in :data:`STAGES` order: adding a stage at the end
    leaves the earlier seeds as they were)."""
    state = np.random.SeedSequence(int(seed)).generate_state(len(STAGES), dtype=np.uint32)
    return {name: int(s) & 0x7FFFFFFF for name, s in zip(STAGES, state, strict=True)}
