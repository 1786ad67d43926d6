"""Jitted edits of the sliding window that the estimator makes every frame: an empty window of
given capacities, inserting a frame with its IMU interval, landmarks and observations, and
pruning after a solve. Fixed shapes throughout (index ``capacity`` means "no slot": those
updates are dropped), so each compiles once per configuration.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu import ImuNoise, Preintegrated, preintegrate
from uavcal_jax.vio.config import CostConfig, SolverConfig
from uavcal_jax.vio.residuals import factor_residuals, landmark_mask
from uavcal_jax.vio.solver import SolveInfo, structured_solve
from uavcal_jax.vio.window import (
    FRAME_DIM,
    CalibParams,
    ImuFactors,
    ImuSamples,
    Keyframes,
    Landmarks,
    Observations,
    Prior,
    WindowProblem,
    WindowState,
)

__all__ = ["empty_window", "insert_frame", "insert_solve_prune", "preintegrate_padded", "prune",
           "window_summary"]


def _identity_frames(n: int) -> Keyframes:
    z = jnp.zeros((n, 3))
    return Keyframes(jnp.broadcast_to(jnp.eye(3), (n, 3, 3)), z, z, z, z)


@functools.partial(jax.jit, static_argnames=("capacity",))
def preintegrate_padded(dt, gyro, accel, mask, bias_gyro, bias_accel, noise: ImuNoise,
                        capacity: int | None = None) -> Preintegrated:
    """:func:`~uavcal_jax.imu.preintegrate` on ``(S,)``-padded samples (jitted; ``capacity``
    only names the static shape in the cache key)."""
    del capacity
    return preintegrate(dt, gyro, accel, bias_gyro, bias_accel, mask=mask, noise=noise, unroll=4)


def empty_window(n_frames: int, n_landmarks: int, n_obs: int, n_samples: int,
                 noise: ImuNoise, cost: CostConfig) -> tuple[WindowState, WindowProblem,
                                                             ImuSamples]:
    """A window with every slot free: ``(state, problem, samples)``."""
    K = n_frames - 1
    dt = jnp.full((K, n_samples), 1e-3)
    zeros3 = jnp.zeros((K, n_samples, 3))
    mask = jnp.zeros((K, n_samples), bool).at[:, 0].set(True)
    pim = jax.vmap(lambda d, g, a, m: preintegrate_padded(d, g, a, m, jnp.zeros(3), jnp.zeros(3),
                                                          noise))(
        dt, zeros3, zeros3 - jnp.array(GRAVITY_W), mask)
    frames = _identity_frames(n_frames)
    D = FRAME_DIM * n_frames
    problem = WindowProblem(
        frame_mask=jnp.zeros(n_frames, bool),
        landmarks=Landmarks(jnp.zeros(n_landmarks, jnp.int32), jnp.zeros((n_landmarks, 2)),
                            jnp.zeros(n_landmarks, bool)),
        observations=Observations(jnp.zeros(n_obs, jnp.int32), jnp.zeros(n_obs, jnp.int32),
                                  jnp.zeros(n_obs, jnp.int32), jnp.zeros((n_obs, 2)),
                                  jnp.zeros(n_obs, bool)),
        imu=ImuFactors(pim, jnp.zeros(K, bool)),
        prior=Prior(jnp.zeros((D, D)), jnp.zeros(D), frames, jnp.asarray(False)),
        config=cost)
    samples = ImuSamples(dt, zeros3, zeros3, jnp.zeros((K, n_samples), bool))
    return WindowState(frames, jnp.ones(n_landmarks)), problem, samples


@jax.jit
def insert_frame(state: WindowState, problem: WindowProblem, samples: ImuSamples, slot,
                 frame: Keyframes, pim: Preintegrated, row: ImuSamples, lm_slot, lm_bearing,
                 lm_inv_depth, obs_slot, obs_landmark, obs_camera, obs_xy
                 ) -> tuple[WindowState, WindowProblem, ImuSamples]:
    """Put a frame into keyframe slot ``slot`` with the IMU interval ``slot - 1 -> slot``
    (``pim``, raw ``row``; none for slot 0), new landmarks anchored in it and its
    observations.

    Args:
        frame: :class:`Keyframes` with no leading axis, the frame's initial state.
        pim, row: the interval's preintegration and samples (no leading axis).
        lm_slot: (K,) int landmark slots to start (``L``: none), ``lm_bearing`` (K, 2),
            ``lm_inv_depth`` (K,) 1/m.
        obs_slot: (Q,) int observation slots to fill (``M``: none) with ``obs_landmark``
            (Q,), ``obs_camera`` (Q,) and ``obs_xy`` (Q, 2); their keyframe is ``slot``.
    """
    N = problem.frame_mask.shape[0]
    frames = jax.tree_util.tree_map(lambda a, x: a.at[slot].set(x), state.frames, frame)
    k = jnp.where(slot > 0, slot - 1, N)  # N - 1 intervals: index N is dropped
    imu = ImuFactors(
        jax.tree_util.tree_map(lambda a, x: a.at[k].set(x, mode="drop"), problem.imu.pim, pim),
        problem.imu.mask.at[k].set(pim.valid, mode="drop"))
    samples = jax.tree_util.tree_map(lambda a, x: a.at[k].set(x, mode="drop"), samples, row)
    lm = problem.landmarks
    landmarks = Landmarks(lm.anchor.at[lm_slot].set(slot, mode="drop"),
                          lm.bearing.at[lm_slot].set(lm_bearing, mode="drop"),
                          lm.mask.at[lm_slot].set(True, mode="drop"))
    inv_depth = state.inv_depth.at[lm_slot].set(lm_inv_depth, mode="drop")
    obs = problem.observations
    observations = Observations(obs.frame.at[obs_slot].set(slot, mode="drop"),
                                obs.landmark.at[obs_slot].set(obs_landmark, mode="drop"),
                                obs.camera.at[obs_slot].set(obs_camera, mode="drop"),
                                obs.xy.at[obs_slot].set(obs_xy, mode="drop"),
                                obs.mask.at[obs_slot].set(True, mode="drop"))
    problem = dataclasses.replace(problem, frame_mask=problem.frame_mask.at[slot].set(True),
                                  landmarks=landmarks, observations=observations, imu=imu)
    return WindowState(frames, inv_depth), problem, samples


@functools.partial(jax.jit, static_argnames=("max_error_px", "min_depth", "max_depth"))
def prune(state: WindowState, problem: WindowProblem, params: CalibParams,
          max_error_px: float = 3.0, min_depth: float = 0.1, max_depth: float = 200.0
          ) -> WindowProblem:
    """After a solve (VINS-Fusion's ``outliersRejection`` and depth checks): observations whose
    reprojection error exceeds ``max_error_px`` leave the window, and so do landmarks whose
    depth in their anchor left the range ``[min_depth, max_depth]`` m (with their
    observations)."""
    res = factor_residuals(state, problem, params)
    err_px = jnp.linalg.norm(res.observation, axis=-1) * problem.config.pixel_sigma
    obs = problem.observations
    lm = problem.landmarks
    rho = state.inv_depth
    lm_ok = lm.mask & (rho > 1.0 / max_depth) & (rho < 1.0 / min_depth) & jnp.isfinite(rho)
    o_mask = obs.mask & (err_px <= max_error_px) & lm_ok[obs.landmark]
    return dataclasses.replace(problem, landmarks=dataclasses.replace(lm, mask=lm_ok),
                               observations=dataclasses.replace(obs, mask=o_mask))


@jax.jit
def window_summary(problem: WindowProblem) -> dict[str, jax.Array]:
    """What the host mirrors after each edit: ``landmark_mask`` (L,), ``observation_mask``
    (M,), ``active_landmarks`` () (observed in the window) and ``rows`` () residual rows in
    use."""
    active = landmark_mask(problem)
    n_obs = jnp.sum(problem.observations.mask)
    n_imu = jnp.sum(problem.imu.mask & problem.frame_mask[:-1] & problem.frame_mask[1:])
    return {"landmark_mask": problem.landmarks.mask, "observation_mask": problem.observations.mask,
            "active_landmarks": jnp.sum(active), "rows": 2 * n_obs + FRAME_DIM * n_imu}


@functools.partial(jax.jit, static_argnames=("solver", "min_depth"))
def insert_solve_prune(state: WindowState, problem: WindowProblem, samples: ImuSamples, slot,
                       frame: Keyframes, pim: Preintegrated, row: ImuSamples, updates: tuple,
                       params: CalibParams, solver: SolverConfig, min_depth: float
                       ) -> tuple[WindowState, WindowProblem, ImuSamples, SolveInfo, dict,
                                  Keyframes]:
    """A frame's whole window edit as one compiled call: :func:`insert_frame` (``updates``:
    its landmark and observation arguments, in order), the structured solve, :func:`prune`
    (``min_depth`` m) and :func:`window_summary`. On XLA:CPU each jitted call and each
    host transfer has a fixed cost comparable to these small kernels, so the estimator makes
    one call per frame and reads the results back in one transfer.

    Returns ``(state, problem, samples, info, summary, newest)``: the solved and pruned
    window, the solve's :class:`SolveInfo`, the summary and the solved keyframe in ``slot``
    (no leading axis).
    """
    state, problem, samples = insert_frame(state, problem, samples, slot, frame, pim, row,
                                           *updates)
    state, info = structured_solve(state, problem, params, solver)
    problem = prune(state, problem, params, min_depth=min_depth)
    newest = jax.tree_util.tree_map(lambda x: x[slot], state.frames)
    return state, problem, samples, info, window_summary(problem), newest
