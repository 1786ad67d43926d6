"""The estimator's window from the frame that opens it to its reset: the device arrays
(:class:`~uavcal_jax.vio.window.WindowState`, :class:`~uavcal_jax.vio.window.WindowProblem`,
:class:`~uavcal_jax.vio.window.ImuSamples`), their host mirror
(:class:`~uavcal_jax.vio.slots.WindowSlots`) and the edits a frame makes to both: open at a
first keyframe, insert-solve-prune a frame, slide, refine the gyro bias once full.

What to do when (the keyframe decision, the failure policy, resets) is the estimator's
(:class:`~uavcal_jax.vio.estimator.StereoVio`); this module only keeps the two sides in step.
Call under ``jax.enable_x64(True)``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.imu import ImuNoise, Preintegrated
from uavcal_jax.vio.body_state import BodyState
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.initialize import gauge_prior, gyro_bias_from_rotations
from uavcal_jax.vio.marginalize import drop_second_newest, marginalize_oldest, slide_imu_samples
from uavcal_jax.vio.slots import WindowSlots
from uavcal_jax.vio.solver import SolveInfo, structured_solve
from uavcal_jax.vio.window import CalibParams, ImuSamples
from uavcal_jax.vio.window_ops import empty_window, insert_frame, insert_solve_prune

__all__ = ["SlidingWindow"]


class SlidingWindow:
    """An empty window of ``config``'s capacities.

    Args:
        config: the estimator's settings (capacities, cost, solver, marginalisation, prior).
        noise: the IMU noise model.  params: the rig (and IMU offset) the solves use.

    Attributes:
        state, problem, samples: the device window.  slots: its host mirror.
    """

    def __init__(self, config: VioConfig, noise: ImuNoise, params: CalibParams):
        self.config, self.noise, self.params = config, noise, params
        with jax.enable_x64(True):
            self.state, self.problem, self.samples = empty_window(
                config.keyframes, config.landmarks, config.observations, config.imu_samples,
                noise, config.cost)
        self.slots = WindowSlots(config.landmarks, config.observations)

    def newest_state(self) -> BodyState:
        """The newest slot's keyframe on the host."""
        return BodyState.from_keyframe(self.slots.times[-1], jax.device_get(self.state.frames),
                                       slot=self.slots.newest)

    def open(self, state: BodyState, updates: tuple) -> None:
        """Put the first keyframe (``state``, with the landmark and observation ``updates`` of
        :meth:`WindowSlots.measurements`) in slot 0 under a gauge prior centred on it."""
        cfg = self.config
        frames = jax.tree_util.tree_map(lambda a, x: a.at[0].set(x), self.state.frames,
                                        state.keyframe())
        self.problem = dataclasses.replace(self.problem,
                                           prior=gauge_prior(frames, cfg.keyframes, cfg.prior))
        self.state = dataclasses.replace(self.state, frames=frames)
        # slot 0 has no IMU interval: these placeholders are dropped by insert_frame
        dummy = jax.tree_util.tree_map(lambda x: x[0], self.problem.imu.pim)
        row0 = jax.tree_util.tree_map(lambda x: x[0], self.samples)
        self.state, self.problem, self.samples = insert_frame(
            self.state, self.problem, self.samples, 0, state.keyframe(), dummy, row0, *updates)
        self.slots.mirror(self.problem)
        self.slots.append(state.t_ns, True)

    def insert_solve(self, predicted: BodyState, pim: Preintegrated, row: ImuSamples,
                     updates: tuple, is_keyframe: bool, prune_min_depth: float
                     ) -> tuple[SolveInfo, int, BodyState]:
        """The frame at ``predicted`` (its IMU interval ``pim`` and full-width ``row``, its
        ``updates``) into the next slot, solved and pruned (landmarks nearer than
        ``prune_min_depth`` m leave). Returns ``(info, active landmarks, solved state)`` on the
        host."""
        self.state, self.problem, self.samples, info, summary, newest = insert_solve_prune(
            self.state, self.problem, self.samples, self.slots.newest + 1, predicted.keyframe(),
            pim, row, updates, self.params, self.config.solver, prune_min_depth)
        info, summary, newest = jax.device_get((info, summary, newest))
        active = self.slots.apply_summary(summary)
        self.slots.append(predicted.t_ns, is_keyframe)
        return info, active, BodyState.from_keyframe(predicted.t_ns, newest)

    def slide(self) -> None:
        """As VINS-Mono: a second-newest frame that is not a keyframe is dropped (its IMU
        intervals merged); else, once the window is full, the oldest keyframe is marginalised
        into the prior. Either frees the newest slot."""
        cfg, slots = self.config, self.slots
        s = slots.newest
        if s >= 1 and not slots.keyframe[s - 1]:
            self.state, self.problem, self.samples = drop_second_newest(
                self.state, self.problem, self.samples, self.noise, self.params,
                cfg.marginalize)
            slots.remove(s - 1)
        elif s == cfg.keyframes - 1:
            self.state, self.problem = marginalize_oldest(self.state, self.problem, self.params,
                                                          cfg.marginalize)
            self.samples = slide_imu_samples(self.samples)
            slots.remove(0)
            slots.filled_once = True
        else:
            return
        slots.mirror(self.problem)

    def refine_gyro_bias(self) -> None:
        """When the window first fills: the gyro bias from the keyframes' (visual) rotations,
        applied to every keyframe, then a re-solve (VINS-Mono's initial gyro-bias step).
        Skipped with fewer than three keyframes, an interval not in use, or a correction that
        is not finite or beyond ``limits.max_bias_gyro``."""
        n = self.slots.newest
        if n < 2:
            return
        f = jax.device_get(self.state.frames)
        pim = jax.device_get(self.problem.imu.pim)
        if not np.asarray(self.problem.imu.mask)[:n].all():
            return
        d = gyro_bias_from_rotations(f.rotation[:n + 1], pim.delta_R[:n], pim.d_R_d_bg[:n])
        if not np.all(np.isfinite(d)) or np.linalg.norm(d) > self.config.limits.max_bias_gyro:
            return
        frames = dataclasses.replace(self.state.frames,
                                     bias_gyro=self.state.frames.bias_gyro + jnp.asarray(d))
        self.state = dataclasses.replace(self.state, frames=frames)
        self.state, _ = structured_solve(self.state, self.problem, self.params,
                                         self.config.solver)
        self.slots.filled_once = True
