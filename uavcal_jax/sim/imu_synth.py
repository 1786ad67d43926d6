"""Synthetic IMU from a continuous-time trajectory, with the EuRoC/Kalibr noise model
(:class:`~uavcal_jax.imu.noise.ImuNoise`) and turn-on biases (:class:`TurnOnBias`).

Exact (noise-free) measurements at time ``t``, in the body (= IMU) frame::

    gyro  = omega_B(t)                              (body angular velocity)
    accel = R_WB(t)^T (a_W(t) - g_W),  g_W = (0, 0, -9.81)

so an IMU at rest reads ``R_WB^T (0, 0, +9.81)``: +9.81 m/s^2 on body z when level.

Noise (per axis, independent), the discrete-time form of ``imu0/sensor.yaml``'s continuous
densities for a sample period ``dt``::

    b_0       ~ N(0, turn_on_sigma^2)                        (constant turn-on bias)
    b_{k+1}   = b_k + random_walk * sqrt(dt_k) * n_k,   n_k ~ N(0, 1)
    measured  = exact + b_k + noise_density / sqrt(dt) * m_k,   m_k ~ N(0, 1)

(``dt`` is the nominal period ``1 / rate_hz`` for the white noise and the actual step for
the bias walk). The true biases ``b_k`` are returned alongside the samples and can be written
with the ground truth (:func:`ground_truth_from_trajectory`), as EuRoC's
``state_groundtruth_estimate0`` does.

Sensor errors beyond the noise (each off unless given to :func:`synthesize_imu`):

- a camera-IMU time offset ``time_offset`` (seconds; Kalibr's ``timeshift_cam_imu``,
  ``t_imu = t_cam + shift``): the trajectory's clock is the cameras' and the ground truth's,
  and the IMU sample stamped ``t`` measures the motion at ``t - time_offset`` (positive: the
  IMU's stamps run late). Stamps whose shifted time falls outside the trajectory read its first
  or last state (``|time_offset| * rate`` samples at one end);
- rotor vibration (:mod:`uavcal_jax.sim.imu_vibration`), added to the exact angular rate and
  specific force: the airframe's motion, so it passes through the intrinsics below; where the
  trajectory rests (rotors idling) optionally another spectrum;
- intrinsics (:class:`ImuIntrinsics`, OpenVINS's "kalibr" model)::

      gyro  = T_w omega + T_g accel_true + b_g + n_g
      accel = T_a accel_true + b_a + n_a

  ``T_w``, ``T_a`` lower triangular (scale on the diagonal, axis misalignment below it),
  ``T_g`` the gyro's g-sensitivity.

Randomness: numpy's ``Generator`` (PCG64), seeded with ``numpy.random.SeedSequence(seed)``
spawned into independent streams for the gyro/accel turn-on biases, bias walks and white
noise, so the same ``seed`` always gives the same samples (and, e.g., changing the white-noise
density does not change the bias walk). The vibration has a seventh stream of the same
``SeedSequence`` (and its spectrum at rest an eighth), so switching it on leaves the noise and
biases as they were.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uavcal_jax.data.euroc_rig import EUROC_IMU_RATE_HZ
from uavcal_jax.data.sequence import GroundTruth, ImuData
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.noise import ImuNoise
from uavcal_jax.sim.imu_vibration import (
    VibrationSpectrum,
    mixed_vibration_samples,
    rest_weight,
    vibration_samples,
)
from uavcal_jax.sim.trajectory import Trajectory, TrajectoryState

#: Index of the vibration's stream among ``SeedSequence(seed).spawn(...)`` (after the six of
#: :func:`imu_noise`).
VIBRATION_STREAM = 6
#: Index of the vibration at rest's stream (after the vibration's).
REST_VIBRATION_STREAM = 7

__all__ = [
    "ImuIntrinsics",
    "SyntheticImu",
    "TurnOnBias",
    "ground_truth_from_trajectory",
    "imu_noise",
    "imu_timestamps",
    "synthesize_imu",
]


@dataclass(frozen=True)
class TurnOnBias:
    """Spread of the constant biases an IMU wakes up with (a simulator setting: a
    ``sensor.yaml`` does not state it, and :class:`~uavcal_jax.imu.noise.ImuNoise` holds only
    what it does).

    Attributes:
        gyro_sigma: rad/s, std of the gyro turn-on bias (the size of the gyro biases EuRoC's
            ground truth reports, up to ~0.08 rad/s).
        accel_sigma: m/s^2, std of the accelerometer turn-on bias.
    """

    gyro_sigma: float = 0.03
    accel_sigma: float = 0.1


@dataclass(frozen=True)
class ImuIntrinsics:
    """Deterministic sensor errors: scale, axis misalignment and the gyro's g-sensitivity, in
    OpenVINS's "kalibr" IMU model (Yang, Geneva, Zuo, Huang, "Online Self-Calibration for
    Visual-Inertial Navigation: Models, Analysis and Degeneracy", IEEE T-RO 2023; OpenVINS
    ``StateOptions::ImuModel::KALIBR``), with the gyro and accelerometer axes otherwise those
    of the IMU frame (``R_IMUtoGYRO`` = identity)::

        gyro  = T_w omega_I + T_g a_I        a_I: true specific force, IMU frame (m/s^2)
        accel = T_a a_I

    OpenVINS estimates ``D_w = T_w^-1`` and ``D_a = T_a^-1`` (lower triangular, 6 numbers
    each, column-wise) and ``T_g`` (9 numbers, column-wise).

    Attributes:
        T_w: (3, 3) lower triangular: ``1 + scale`` on the diagonal, misalignment below.
        T_a: (3, 3) lower triangular, likewise for the accelerometer.
        T_g: (3, 3) rad/s per m/s^2, g-sensitivity (``gyro += T_g a_I``).
    """

    T_w: np.ndarray
    T_a: np.ndarray
    T_g: np.ndarray

    @classmethod
    def from_errors(cls, scale=None, misalignment=None, g_sensitivity=None) -> ImuIntrinsics:
        """From the simulator's flat settings (``None``: that error is absent).

        Args:
            scale: 6 fractions, gyro x, y, z then accel x, y, z: ``T[i, i] = 1 + scale[i]``
                (1e-3 = 1000 ppm).
            misalignment: 6 numbers (rad, small angles), gyro ``T_w[1,0], T_w[2,0],
                T_w[2,1]`` then accel ``T_a[1,0], T_a[2,0], T_a[2,1]``: how much of an
                earlier axis's input each later axis reads (the strictly lower triangle).
            g_sensitivity: 9 numbers, ``T_g`` row-major, rad/s per m/s^2.
        """
        s = np.zeros(6) if scale is None else np.asarray(scale, dtype=np.float64)
        m = np.zeros(6) if misalignment is None else np.asarray(misalignment, dtype=np.float64)
        if s.shape != (6,) or m.shape != (6,):
            raise ValueError("scale and misalignment must have 6 numbers each")
        rows, cols = np.tril_indices(3, -1)
        T = [np.diag(1.0 + s[3 * k:3 * k + 3]) for k in range(2)]
        for k in range(2):
            T[k][rows, cols] = m[3 * k:3 * k + 3]
        T_g = (np.zeros((3, 3)) if g_sensitivity is None
               else np.asarray(g_sensitivity, dtype=np.float64).reshape(3, 3))
        return cls(T_w=T[0], T_a=T[1], T_g=T_g)

    def apply(self, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) true angular rate (rad/s) and specific force (m/s^2), IMU frame -> what the
        sensor reads (before biases and noise)."""
        return gyro @ self.T_w.T + accel @ self.T_g.T, accel @ self.T_a.T


@dataclass(frozen=True)
class SyntheticImu:
    """Synthetic IMU samples and the true biases inside them.

    Attributes:
        imu: the measurements (``t_ns`` int64, ``gyro``/``accel`` (N, 3)).
        bias_gyro: (N, 3) rad/s, the gyro bias in each sample (zeros without noise).
        bias_accel: (N, 3) m/s^2.
    """

    imu: ImuData
    bias_gyro: np.ndarray
    bias_accel: np.ndarray


def imu_timestamps(t_start: float, t_end: float, rate_hz: float) -> np.ndarray:
    """int64 ns times ``start_ns + k * round(1e9 / rate_hz)`` within ``[t_start, t_end]``."""
    if rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    period_ns = int(round(1e9 / rate_hz))
    start_ns = int(math.ceil(t_start * 1e9 - 1e-3))
    end_ns = int(math.floor(t_end * 1e9 + 1e-3))
    if end_ns < start_ns:
        raise ValueError(f"empty IMU span [{t_start}, {t_end}]")
    n = (end_ns - start_ns) // period_ns + 1
    return start_ns + period_ns * np.arange(n, dtype=np.int64)


def _measurements(state: TrajectoryState) -> tuple[np.ndarray, np.ndarray]:
    accel = np.einsum("...ji,...j->...i", state.rotation,
                      state.acceleration - np.asarray(GRAVITY_W))
    return state.angular_velocity_body, accel


def imu_noise(n: int, dt: float, noise: ImuNoise, seed: int = 0,
              steps: np.ndarray | None = None, turn_on: TurnOnBias = TurnOnBias()
              ) -> dict[str, np.ndarray]:
    """Noise alone for ``n`` samples: white noise and bias (turn-on + random walk) per sensor.

    Args:
        n: number of samples.
        dt: nominal sample period (seconds) for the white noise.
        noise: the model (scalar densities).
        seed: see the module docstring.
        steps: (n - 1,) actual periods for the bias walk (default: ``dt`` each).
        turn_on: spread of the initial biases.

    Returns:
        ``{"white_gyro", "white_accel", "bias_gyro", "bias_accel"}``, each (n, 3).
    """
    ss = np.random.SeedSequence(seed)
    g_on, a_on, g_walk, a_walk, g_white, a_white = (np.random.default_rng(s)
                                                     for s in ss.spawn(6))
    steps = np.full(max(n - 1, 0), dt) if steps is None else np.asarray(steps, dtype=np.float64)
    sqrt_steps = np.sqrt(steps)[:, None]

    def bias(rng_on, rng_walk, sigma_on, walk):
        b0 = rng_on.normal(size=(1, 3)) * sigma_on
        inc = rng_walk.normal(size=(max(n - 1, 0), 3)) * walk * sqrt_steps
        return b0 + np.concatenate([np.zeros((1, 3)), np.cumsum(inc, axis=0)], axis=0)[:n]

    return {
        "white_gyro": g_white.normal(size=(n, 3)) * noise.gyro_noise_density / math.sqrt(dt),
        "white_accel": a_white.normal(size=(n, 3)) * noise.accel_noise_density / math.sqrt(dt),
        "bias_gyro": bias(g_on, g_walk, turn_on.gyro_sigma, noise.gyro_random_walk),
        "bias_accel": bias(a_on, a_walk, turn_on.accel_sigma, noise.accel_random_walk),
    }


def synthesize_imu(traj: Trajectory, rate_hz: float = EUROC_IMU_RATE_HZ,
                   noise: ImuNoise | None = None, seed: int = 0,
                   t_start: float | None = None, t_end: float | None = None,
                   *, t_ns: np.ndarray | None = None, turn_on: TurnOnBias = TurnOnBias(),
                   time_offset: float = 0.0, vibration: VibrationSpectrum | None = None,
                   rest_vibration: VibrationSpectrum | None = None,
                   vibration_scale: float = 1.0, intrinsics: ImuIntrinsics | None = None
                   ) -> SyntheticImu:
    """IMU samples of a trajectory at ``rate_hz`` (or at given times).

    Args:
        traj: the trajectory.
        rate_hz: sample rate; samples at ``ceil(t_start in ns) + k * round(1e9 / rate_hz)``.
        noise: the noise model, or ``None`` for exact measurements (zero biases).
        seed: noise seed (numpy ``Generator``; see the module docstring).
        t_start, t_end: span in seconds (default: the trajectory's).
        t_ns: explicit int64 ns sample times instead of the regular grid (e.g. a real IMU's).
        turn_on: spread of the initial biases (with ``noise`` only).
        time_offset: seconds, Kalibr's ``timeshift_cam_imu`` (``t_imu = t_cam + shift``): the
            sample stamped ``t`` measures the motion at ``t - time_offset`` (module docstring).
        vibration: rotor vibration added to the motion (``None``: none), its amplitudes times
            ``vibration_scale``; drawn from ``seed``'s vibration stream.
        rest_vibration: with ``vibration``, the spectrum where the trajectory rests (rotors
            idling; :func:`~uavcal_jax.sim.imu_vibration.rest_weight`), drawn from its own
            stream; ``None``: ``vibration`` throughout. A trajectory that never rests gives
            the samples it gives without.
        intrinsics: scale, misalignment and g-sensitivity (``None``: an ideal sensor).

    Returns:
        :class:`SyntheticImu` (its ``t_ns`` are the stamps, unshifted).
    """
    if t_ns is None:
        t0 = traj.t_start if t_start is None else float(t_start)
        t1 = traj.t_end if t_end is None else float(t_end)
        t_ns = imu_timestamps(t0, t1, rate_hz)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if t_ns.ndim != 1 or len(t_ns) == 0 or np.any(np.diff(t_ns) <= 0):
        raise ValueError("t_ns must be a non-empty, strictly increasing (N,) array")
    n = len(t_ns)
    if time_offset:
        shift_ns = int(round(time_offset * 1e9))
        t_lo, t_hi = (int(math.ceil(traj.t_start * 1e9)), int(math.floor(traj.t_end * 1e9)))
        state = traj.state_ns(np.clip(t_ns - shift_ns, t_lo, t_hi))
    else:
        state = traj.state_ns(t_ns)
    gyro, accel = _measurements(state)
    if vibration is not None and vibration_scale:
        streams = np.random.SeedSequence(seed).spawn(REST_VIBRATION_STREAM + 1)
        rng, rng_rest = (np.random.default_rng(streams[i])
                         for i in (VIBRATION_STREAM, REST_VIBRATION_STREAM))
        if rest_vibration is None:
            vib_gyro, vib_accel = vibration_samples(vibration, n, rate_hz, rng, vibration_scale)
        else:
            weight = rest_weight(state.position, state.angular_velocity_body, rate_hz)
            vib_gyro, vib_accel = mixed_vibration_samples(vibration, rest_vibration, weight,
                                                          rate_hz, rng, rng_rest,
                                                          vibration_scale)
        gyro, accel = gyro + vib_gyro, accel + vib_accel
    if intrinsics is not None:
        gyro, accel = intrinsics.apply(gyro, accel)
    if noise is None:
        zeros = np.zeros((n, 3))
        return SyntheticImu(ImuData(t_ns=t_ns, gyro=gyro, accel=accel), zeros, zeros.copy())
    dt = 1.0 / rate_hz
    nz = imu_noise(n, dt, noise, seed, steps=np.diff(t_ns).astype(np.float64) * 1e-9,
                   turn_on=turn_on)
    gyro = gyro + nz["bias_gyro"] + nz["white_gyro"]
    accel = accel + nz["bias_accel"] + nz["white_accel"]
    return SyntheticImu(ImuData(t_ns=t_ns, gyro=gyro, accel=accel),
                        nz["bias_gyro"], nz["bias_accel"])


def ground_truth_from_trajectory(traj: Trajectory, t_ns, bias_gyro=None, bias_accel=None, *,
                                 bias_t_ns=None) -> GroundTruth:
    """Ground-truth states (EuRoC's 17 columns) of a trajectory at int64 ns times.

    Args:
        traj: the trajectory.
        t_ns: (N,) int64 nanoseconds inside the trajectory's span.
        bias_gyro, bias_accel: the true IMU biases, (N, 3) at ``t_ns`` -- or at ``bias_t_ns``
            (e.g. the IMU's times), then linearly interpolated (held constant outside).
            ``None`` means zero (an exact IMU).
        bias_t_ns: see above.

    Returns:
        ``GroundTruth`` with position, unit quaternion (w, x, y, z; sign-continuous), world
        velocity and both biases filled in.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    state = traj.state_ns(t_ns)
    n = len(t_ns)

    def bias(b):
        if b is None:
            return np.zeros((n, 3))
        b = np.asarray(b, dtype=np.float64)
        if bias_t_ns is not None:
            src = np.asarray(bias_t_ns, dtype=np.int64)
            if b.shape != (len(src), 3):
                raise ValueError(f"bias shape {b.shape} does not match bias_t_ns ({len(src)})")
            x = (src - src[0]).astype(np.float64)
            xi = (t_ns - src[0]).astype(np.float64)
            return np.stack([np.interp(xi, x, b[:, j]) for j in range(3)], axis=1)
        if b.shape != (n, 3):
            raise ValueError(f"bias shape {b.shape} does not match t_ns ({n})")
        return b.copy()

    return GroundTruth(t_ns=t_ns, position=state.position, quaternion=state.quaternion,
                       velocity=state.velocity, bias_gyro=bias(bias_gyro),
                       bias_accel=bias(bias_accel))
