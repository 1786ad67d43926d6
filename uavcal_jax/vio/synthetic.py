"""An exactly consistent synthetic window (tests, benchmarks): closed-form flight, landmarks in
front of a stereo rig, noisy stereo and temporal observations, preintegrated IMU intervals.

The body follows ``p(t) = p0 + A sin(w t + phase)`` and ``R(t) = R0 exp(phi(t))`` with small
sinusoidal ``phi``; ``R0`` points camera 0's optical axis along world +x, level. The gyro
reads ``Jr(phi) phi'`` and the accelerometer ``R^T (p'' - g)``, sampled at interval midpoints
(plus ``imu_offset``). The true keyframe states are chained by
:func:`uavcal_jax.imu.predict` from the true state at ``t = 0`` through the offset-free
intervals, so the IMU residual is exactly zero at the truth (and at the true offset, to first
order). Landmarks are drawn as a pixel and a depth in camera 0 of an anchor keyframe, tracked
for a few keyframes in both cameras while visible; pixels (with the lens distortion) get
Gaussian noise and are undistorted with :mod:`uavcal_jax.geometry.camera`, the anchor's
bearing included. A prior on keyframe 0 (centred on a draw from its own sigmas) fixes the
gauge, as a marginalisation prior does. Call under ``jax.enable_x64(True)``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc_rig import (
    EUROC_CAM0_T_BS,
    EUROC_CAM1_T_BS,
    EUROC_IMU_RATE_HZ,
    euroc_calibration,
    euroc_camera,
)
from uavcal_jax.geometry.camera import pixels_to_normalized, project
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu import EUROC_ADIS16448, NavState, predict, preintegrate
from uavcal_jax.vio.config import CostConfig, resolve_cost
from uavcal_jax.vio.window import (
    FRAME_DIM,
    CalibParams,
    ImuFactors,
    Keyframes,
    Landmarks,
    Observations,
    Prior,
    WindowProblem,
    WindowState,
    retract,
    retract_frames,
)

__all__ = ["SyntheticConfig", "SyntheticWindow", "euroc_params", "imu_samples", "perturb",
           "synthetic_window"]

_AMP = np.array([0.3, 0.6, 0.2])
_OMEGA = np.array([1.1, 0.9, 1.7])
_PHASE = np.array([0.0, 0.3, 0.5])
_ROT_AMP = np.array([0.15, 0.1, 0.2])
_ROT_OMEGA = np.array([1.3, 0.7, 0.9])
_ROT_PHASE = np.array([0.0, 1.0, 0.2])
# camera 0 looking along world +x, image x to world -y, image y (down) to world -z
_R_WC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Size and noise of the synthetic window.

    Attributes:
        n_frames, n_landmarks: capacities ``N`` and ``L`` (all slots used).
        keyframe_dt: seconds between keyframes.  imu_rate_hz: IMU sample rate.
        pixel_sigma: feature noise, pixels.  depth_range: landmark depths, m.
        track_length: (min, max) keyframes a landmark is tracked for, anchor included.
        prior_sigma: (15,) prior sigmas on keyframe 0 (rotation rad, position m, velocity
            m/s, gyro bias rad/s, accel bias m/s^2).
        imu_offset: (6,) offset added to the IMU samples.
        obs_capacity: observation slots ``M`` (``None``: exactly the observations made).
    """

    n_frames: int = 5
    n_landmarks: int = 60
    keyframe_dt: float = 0.2
    imu_rate_hz: float = EUROC_IMU_RATE_HZ
    pixel_sigma: float = 0.5
    depth_range: tuple[float, float] = (2.0, 8.0)
    track_length: tuple[int, int] = (3, 10)
    prior_sigma: tuple[float, ...] = (2e-3,) * 3 + (5e-3,) * 3 + (1e-2,) * 3 + (1e-3,) * 3 + (
        1e-2,) * 3
    imu_offset: tuple[float, ...] = (0.0,) * 6
    obs_capacity: int | None = None


@dataclasses.dataclass(frozen=True)
class SyntheticWindow:
    """``truth`` (:class:`WindowState`), ``problem``, ``params`` (the true rig and offset) and
    ``points`` (L, 3) world landmarks (numpy)."""

    truth: WindowState
    problem: WindowProblem
    params: CalibParams
    points: np.ndarray


def _flight(t):
    """Position, velocity, acceleration (..., 3), rotation (..., 3, 3), body rate (..., 3)."""
    t = np.asarray(t, np.float64)[..., None]
    arg = _OMEGA * t + _PHASE
    p = np.array([0.0, 0.0, 1.0]) + _AMP * np.sin(arg)
    v = _AMP * _OMEGA * np.cos(arg)
    a = -_AMP * _OMEGA**2 * np.sin(arg)
    rarg = _ROT_OMEGA * t + _ROT_PHASE
    phi = _ROT_AMP * np.sin(rarg)
    dphi = _ROT_AMP * _ROT_OMEGA * np.cos(rarg)
    R_B0 = _R_WC @ EUROC_CAM0_T_BS[:3, :3].T
    R = R_B0 @ Rotation.from_rotvec(phi.reshape(-1, 3)).as_matrix().reshape(phi.shape + (3,))
    return p, v, a, R, np.einsum("...ij,...j->...i", _right_jacobian(phi), dphi)


def _right_jacobian(phi):
    """``Jr(phi)`` (..., 3, 3) in numpy (phi away from zero is not needed: |phi| > 0 here is
    handled by the series-free closed form with a small-angle guard)."""
    t = np.linalg.norm(phi, axis=-1)[..., None, None]
    t = np.maximum(t, 1e-9)
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    o = np.zeros_like(x)
    W = np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1),
                  np.stack([-y, x, o], -1)], -2)
    return np.eye(3) - (1 - np.cos(t)) / t**2 * W + (t - np.sin(t)) / t**3 * (W @ W)


def imu_samples(cfg: SyntheticConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact IMU samples of every keyframe interval: ``dt (n_frames - 1, n)`` seconds,
    ``gyro (n_frames - 1, n, 3)`` rad/s and ``accel (n_frames - 1, n, 3)`` m/s^2 in the body
    frame, each sampled at the midpoint of the step it is held for."""
    n = int(round(cfg.keyframe_dt * cfg.imu_rate_hz))
    h = cfg.keyframe_dt / n
    t = cfg.keyframe_dt * np.arange(cfg.n_frames - 1)[:, None] + h * (np.arange(n) + 0.5)
    _, _, a, R, omega = _flight(t)
    accel = np.einsum("...ji,...j->...i", R, a - np.asarray(GRAVITY_W))
    return np.full(t.shape, h), omega, accel


_project = jax.jit(project)
_normalized = jax.jit(pixels_to_normalized)


def euroc_params(dtype=None) -> CalibParams:
    """EuRoC's stereo rig (cam0 and cam1 ``T_BS``) and a zero offset: the rig of the
    synthetic window (the estimator takes the recording's own, never this one)."""
    dtype = dtype or jnp.result_type(float)
    T = np.stack([EUROC_CAM0_T_BS, EUROC_CAM1_T_BS])
    return CalibParams(jnp.zeros(6, dtype), jnp.asarray(T[:, :3, :3], dtype),
                       jnp.asarray(T[:, :3, 3], dtype))


def _pick(tree, k):
    return jax.tree_util.tree_map(lambda x: x[k], tree)


def synthetic_window(config: SyntheticConfig | None = None, seed: int = 0,
                     cost_config: CostConfig | None = None, noise=None) -> SyntheticWindow:
    """Build the window (see the module docstring). ``noise``: the IMU noise model of the
    preintegration (``None``: EuRoC's ADIS16448);
    ``config`` and ``cost_config`` default to their classes' defaults; an unset
    ``cost_config.focal_px`` becomes EuRoC cam0's ``fx`` (the window's rig)."""
    config = SyntheticConfig() if config is None else config
    cost_config = resolve_cost(CostConfig() if cost_config is None else cost_config,
                               euroc_calibration(0))
    noise = EUROC_ADIS16448 if noise is None else noise
    rng = np.random.default_rng(seed)
    N, L = config.n_frames, config.n_landmarks
    params = euroc_params(jnp.float64)
    cams = (euroc_camera(0, jnp.float64), euroc_camera(1, jnp.float64))
    off = np.asarray(config.imu_offset, np.float64)

    dt, gyro, accel = imu_samples(config)
    clean = preintegrate(dt, gyro, accel, noise=noise)
    pim = (preintegrate(dt, gyro + off[:3], accel + off[3:], noise=noise) if np.any(off)
           else clean)

    p, v, _, R, _ = _flight(np.zeros(1))
    states = [NavState(jnp.asarray(R[0]), jnp.asarray(p[0]), jnp.asarray(v[0]))]
    for k in range(N - 1):
        states.append(predict(states[-1], _pick(clean, k), jnp.zeros(6)))
    zeros = jnp.zeros((N, 3))
    frames = Keyframes(jnp.stack([s.rotation for s in states]),
                       jnp.stack([s.position for s in states]),
                       jnp.stack([s.velocity for s in states]), zeros, zeros)
    Rw, pw = np.asarray(frames.rotation), np.asarray(frames.position)
    R_BC, t_BC = np.asarray(params.R_BC), np.asarray(params.t_BC)

    def measure(P_c, c):
        """Noisy undistorted normalised coordinates (K, 2) of camera-frame points (K, 3)."""
        uv = np.asarray(_project(jnp.asarray(P_c), cams[c]))
        inside = ((P_c[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < cams[c].width)
                  & (uv[:, 1] >= 0) & (uv[:, 1] < cams[c].height))
        uv = uv + config.pixel_sigma * rng.standard_normal(uv.shape)
        return inside, np.asarray(_normalized(jnp.asarray(uv), cams[c]))

    lo, hi = config.track_length
    anchor = rng.integers(0, max(1, N - lo + 1), L)
    margin = 20.0
    uv0 = rng.uniform([margin, margin], [cams[0].width - margin, cams[0].height - margin], (L, 2))
    depth = rng.uniform(*config.depth_range, L)
    xy0 = np.asarray(_normalized(jnp.asarray(uv0), cams[0]))
    P_a = depth[:, None] * np.concatenate([xy0, np.ones((L, 1))], 1)
    points = np.einsum("lij,lj->li", Rw[anchor], P_a @ R_BC[0].T + t_BC[0]) + pw[anchor]
    inv_depth = 1.0 / depth
    bearing = measure(P_a, 0)[1]
    cand = []
    for l in range(L):
        a = int(anchor[l])
        length = int(rng.integers(lo, max(lo, min(hi, N - a)) + 1))
        cand += [(f, l, c) for f in range(a, min(N, a + length)) for c in (0, 1)
                 if not (f == a and c == 0)]
    cand = np.array(cand, np.int64).reshape(-1, 3)
    keep, xy = np.zeros(len(cand), bool), np.zeros((len(cand), 2))
    for c in (0, 1):
        sel = cand[:, 2] == c
        f, l = cand[sel, 0], cand[sel, 1]
        P_b = np.einsum("kji,kj->ki", Rw[f], points[l] - pw[f])
        keep[sel], xy[sel] = measure((P_b - t_BC[c]) @ R_BC[c], c)
    obs = [(int(f), int(l), int(c), q)
           for (f, l, c), q in zip(cand[keep], xy[keep], strict=True)]
    M = config.obs_capacity or len(obs)
    if len(obs) > M:
        raise ValueError(f"obs_capacity {M} < {len(obs)} observations made")
    pad = M - len(obs)
    o_f = np.array([o[0] for o in obs] + [0] * pad, np.int32)
    o_l = np.array([o[1] for o in obs] + [0] * pad, np.int32)
    o_c = np.array([o[2] for o in obs] + [0] * pad, np.int32)
    o_xy = np.array([o[3] for o in obs] + [np.zeros(2)] * pad)
    o_m = np.arange(M) < len(obs)
    seen = np.zeros(L, bool)
    seen[o_l[o_m]] = True

    sigma = np.asarray(config.prior_sigma, np.float64)
    e = np.zeros((N, FRAME_DIM))
    e[0] = sigma * rng.standard_normal(FRAME_DIM)
    J = np.zeros((N * FRAME_DIM, N * FRAME_DIM))
    J[:FRAME_DIM, :FRAME_DIM] = np.diag(1.0 / sigma)
    prior = Prior(jnp.asarray(J), jnp.zeros(N * FRAME_DIM),
                  retract_frames(frames, jnp.asarray(e)), jnp.asarray(True))

    problem = WindowProblem(
        frame_mask=jnp.ones(N, bool),
        landmarks=Landmarks(jnp.asarray(anchor, jnp.int32), jnp.asarray(bearing),
                            jnp.asarray(seen)),
        observations=Observations(jnp.asarray(o_f), jnp.asarray(o_l), jnp.asarray(o_c),
                                  jnp.asarray(o_xy), jnp.asarray(o_m)),
        imu=ImuFactors(pim, jnp.ones(N - 1, bool)),
        prior=prior,
        config=cost_config,
    )
    truth = WindowState(frames, jnp.asarray(inv_depth))
    params = dataclasses.replace(params, imu_offset=jnp.asarray(off))
    return SyntheticWindow(truth, problem, params, points)


def perturb(state: WindowState, seed: int, rotation=0.01, position=0.05, velocity=0.05,
            bias_gyro=1e-3, bias_accel=1e-2, inv_depth=0.1) -> WindowState:
    """``state`` moved by Gaussian draws with these sigmas (rad, m, m/s, rad/s, m/s^2) and
    inverse depths scaled by ``1 + inv_depth * N(0, 1)``: a warm start to solve from."""
    rng = np.random.default_rng(seed)
    N, L = state.frames.position.shape[0], state.inv_depth.shape[0]
    s = np.repeat([rotation, position, velocity, bias_gyro, bias_accel], 3)
    d_f = jnp.asarray(s * rng.standard_normal((N, FRAME_DIM)))
    d_l = state.inv_depth * inv_depth * jnp.asarray(rng.standard_normal(L))
    return retract(state, d_f, d_l)
