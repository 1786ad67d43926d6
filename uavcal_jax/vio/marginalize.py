"""Sliding the window: marginalisation of the oldest keyframe into a linear prior, and the
drop of the second-newest frame (VINS-Mono / VINS-Fusion's ``MARGIN_OLD`` and
``MARGIN_SECOND_NEW``).

Both act on a window whose slots ``0 .. n`` are in use, contiguously (``n + 1`` frames, the
newest in slot ``n``; VINS-Fusion slides once the window is full, ``n = N - 1``), and keep every
capacity: slots stay, masks change. Afterwards slot ``n`` is free for the next frame.

**Oldest keyframe** (:func:`marginalize_oldest`, the newest frame is a keyframe). The factors
touching keyframe 0 are linearised at the current estimate: the IMU interval 0 -> 1, every
reprojection factor of the landmarks anchored in keyframe 0 or observed by it, and the
existing prior (VINS-Fusion's ``MarginalizationInfo::addResidualBlockInfo`` set). Their
Gauss-Newton information ``(H, b)`` (``b`` the gradient, IRLS weights of the robust function
included, as VINS-Fusion's loss-scaled Jacobians) over all frames and those landmarks is
reduced by Schur complement: first the landmarks (a diagonal block), then keyframe 0's 15 x
15 block, with an eigen-clipped pseudo-inverse of the eliminated block as
``MarginalizationInfo::marginalize``. The result becomes the new :class:`Prior` on the
surviving frames with its linearisation point fixed at the current estimate (first-estimate
Jacobians: later solves evaluate ``r_p + J_p (x ⊟ x_lin)`` and never re-linearise it).

The eliminated landmarks leave the window: all their observations went into the prior.
VINS-Fusion instead re-anchors them in the next observing frame and keeps using their later
observations, which counts those measurements twice (once in the prior, once as factors);
dropping them keeps the prior exact, and the front end re-creates a still-tracked corner as a
new landmark. Everything else shifts one slot down: keyframes, IMU intervals, landmark anchors
and observation frames.

**Second-newest frame** (:func:`drop_second_newest`, the newest frame is not a keyframe).
Frame ``n - 1`` is removed and its visual measurements discarded, no information kept from
them (VINS-Mono); if the prior involves the frame, the frame is marginalised out of the prior
alone (VINS-Mono's ``drop_set``). Its two IMU intervals are merged by re-preintegrating
their concatenated raw samples from :class:`~uavcal_jax.vio.window.ImuSamples` (VINS-Mono's
``push_back`` of the buffered samples onto interval ``n - 2``), at that interval's
integration biases. A landmark anchored in the dropped frame is re-anchored in the newest
frame's left-camera observation (VINS-Mono's ``removeFront``: ``start_frame--``), its inverse
depth carried over through the current estimate; without such an observation it is dropped.

All functions are pure and jit-able with static shapes; call them under
``jax.enable_x64(True)`` as the rest of the back end.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from uavcal_jax.imu import ImuNoise, preintegrate
from uavcal_jax.vio.config import MarginalizeConfig
from uavcal_jax.vio.normal import normal_equations
from uavcal_jax.vio.residuals import imu_mask, observation_mask
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
    prior_from_information,
)

__all__ = [
    "drop_second_newest",
    "equilibrated_pinv",
    "equilibrated_prior",
    "marginal_information",
    "marginalize_oldest",
    "slide_imu_samples",
]

_D = FRAME_DIM


# --- helpers ---------------------------------------------------------------------------------


def equilibrated_pinv(A: jax.Array, eps: float) -> jax.Array:
    """Pseudo-inverse of the symmetric PSD ``A`` (n, n) through the eigen-decomposition of
    ``D^-1/2 A D^-1/2`` (``D = diag A``), eigenvalues below ``eps`` dropped."""
    d = jnp.diag(A)
    s = jnp.where(d > 0, 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 0.0)
    As = s[:, None] * A * s[None, :]
    lam, V = jnp.linalg.eigh(0.5 * (As + As.T))
    inv = jnp.where(lam > eps, 1.0 / jnp.where(lam > eps, lam, 1.0), 0.0)
    return s[:, None] * ((V * inv[None, :]) @ V.T) * s[None, :]


def equilibrated_prior(H: jax.Array, b: jax.Array, lin: Keyframes, eps: float) -> Prior:
    """:func:`prior_from_information` on ``D^-1/2 H D^-1/2`` and ``D^-1/2 b`` in the scaled
    variable ``e = D^1/2 d``, its Jacobian mapped back (``J = J_e D^1/2``): the same quadratic,
    with the eigen-decomposition's error relative to each entry's own scale."""
    d = jnp.diag(H)
    pos = d > 0
    sq = jnp.where(pos, jnp.sqrt(jnp.where(pos, d, 1.0)), 0.0)
    inv = jnp.where(pos, 1.0 / jnp.where(pos, sq, 1.0), 0.0)
    prior = prior_from_information(inv[:, None] * H * inv[None, :], inv * b, lin, eps)
    return dataclasses.replace(prior, J=prior.J * sq[None, :])


def _shift_down(x: jax.Array) -> jax.Array:
    """``x[1:]`` followed by a copy of ``x[-1]`` (the freed last slot keeps finite values)."""
    return jnp.concatenate([x[1:], x[-1:]], axis=0)


def _tree_shift_down(tree):
    return jax.tree_util.tree_map(_shift_down, tree)


# --- oldest keyframe -------------------------------------------------------------------------


def _marginalised_landmarks(problem: WindowProblem) -> jax.Array:
    """(L,) bool: landmarks in use anchored in keyframe 0 or observed by it."""
    L = problem.landmarks.mask.shape[0]
    om = observation_mask(problem)
    seen0 = jax.ops.segment_sum((om & (problem.observations.frame == 0)).astype(jnp.int32),
                                problem.observations.landmark, num_segments=L) > 0
    return problem.landmarks.mask & ((problem.landmarks.anchor == 0) | seen0)


@functools.partial(jax.jit, static_argnames=("config",))
def marginal_information(state: WindowState, problem: WindowProblem, params: CalibParams,
                         config: MarginalizeConfig = MarginalizeConfig()  # noqa: B008
                         ) -> tuple[jax.Array, jax.Array]:
    """``(H (15N, 15N), b (15N,))``: the information of the factors touching keyframe 0 after
    eliminating keyframe 0 and its landmarks, in the *unshifted* slots (rows and columns of
    keyframe 0 and of unused slots are zero). The quadratic is ``0.5 d^T H d + b^T d`` in the
    tangent ``d`` at ``state``."""
    N = problem.frame_mask.shape[0]
    elim = _marginalised_landmarks(problem)
    sub = dataclasses.replace(
        problem,
        observations=dataclasses.replace(
            problem.observations,
            mask=observation_mask(problem) & elim[problem.observations.landmark]),
        imu=dataclasses.replace(problem.imu,
                                mask=imu_mask(problem) & (jnp.arange(N - 1) == 0)))
    neq = normal_equations(state, sub, params)
    fa = neq.frame_active
    H = neq.H_ff - jnp.diag(jnp.where(fa, 0.0, 1.0))
    # landmarks: H_ll is diagonal; the relative threshold compares each one's information with
    # the largest landmark information of the window
    use = neq.landmark_active
    h_ll = jnp.where(use, neq.H_ll, 0.0)
    ok = use & (h_ll > config.pinv_eps * jnp.max(h_ll))
    inv_ll = jnp.where(ok, 1.0 / jnp.where(ok, h_ll, 1.0), 0.0)
    W = neq.H_fl * inv_ll[None, :]
    S = H - W @ neq.H_fl.T
    g = neq.g_f - W @ neq.g_l
    S = 0.5 * (S + S.T)
    # keyframe 0
    Smm_inv = equilibrated_pinv(S[:_D, :_D], config.pinv_eps)
    K = S[_D:, :_D] @ Smm_inv
    Hr = S[_D:, _D:] - K @ S[:_D, _D:]
    br = g[_D:] - K @ g[:_D]
    Hr = 0.5 * (Hr + Hr.T)
    keep = fa[_D:]
    Hr = jnp.where(keep[:, None] & keep[None, :], Hr, 0.0)
    br = jnp.where(keep, br, 0.0)
    H_out = jnp.zeros_like(H).at[_D:, _D:].set(Hr)
    b_out = jnp.zeros_like(g).at[_D:].set(br)
    return H_out, b_out


def marginalize_oldest(state: WindowState, problem: WindowProblem, params: CalibParams,
                       config: MarginalizeConfig = MarginalizeConfig()  # noqa: B008
                       ) -> tuple[WindowState, WindowProblem]:
    """Marginalise keyframe 0 into the prior and shift the window one slot down.

    Returns ``(state', problem')``: slot ``k`` of ``state'`` is slot ``k + 1`` of ``state``
    (the last slot is free, a copy of the old last one), the landmarks anchored in or observed
    by keyframe 0 are masked off (their information is in the prior), and ``problem'.prior`` is
    the new linear prior with ``lin = state'.frames``. ``params`` (the rig and IMU offset) is
    the one the solves use. Raw IMU samples, when kept, shift with :func:`slide_imu_samples`.
    """
    # two jitted halves rather than one: marginal_information is compiled once and shared
    # with callers that want the information itself
    H, b = marginal_information(state, problem, params, config)
    return _shift_oldest(state, problem, H, b, config)


@functools.partial(jax.jit, static_argnames=("config",))
def _shift_oldest(state, problem, H, b, config):
    H = jnp.roll(jnp.roll(H, -_D, axis=0), -_D, axis=1)
    b = jnp.roll(b, -_D)
    frames = _tree_shift_down(state.frames)
    prior = equilibrated_prior(H, b, frames, config.prior_eps)

    elim = _marginalised_landmarks(problem)
    lm = problem.landmarks
    lm_mask = lm.mask & ~elim & (lm.anchor >= 1)
    landmarks = Landmarks(jnp.maximum(lm.anchor - 1, 0), lm.bearing, lm_mask)
    obs = problem.observations
    obs_mask = obs.mask & (obs.frame >= 1) & lm_mask[obs.landmark]
    observations = dataclasses.replace(obs, frame=jnp.maximum(obs.frame - 1, 0), mask=obs_mask)
    imu = ImuFactors(_tree_shift_down(problem.imu.pim),
                     jnp.concatenate([problem.imu.mask[1:], jnp.zeros(1, bool)]))
    frame_mask = jnp.concatenate([problem.frame_mask[1:], jnp.zeros(1, bool)])
    new_problem = dataclasses.replace(problem, frame_mask=frame_mask, landmarks=landmarks,
                                      observations=observations, imu=imu, prior=prior)
    return WindowState(frames, state.inv_depth), new_problem


@jax.jit
def slide_imu_samples(samples: ImuSamples) -> ImuSamples:
    """The raw samples shifted as :func:`marginalize_oldest` shifts the intervals (interval 0
    leaves, the last one is freed with its mask cleared)."""
    out = _tree_shift_down(samples)
    return dataclasses.replace(out, mask=out.mask.at[-1].set(False))


# --- second-newest frame ---------------------------------------------------------------------


def _merge_samples(samples: ImuSamples, i: jax.Array) -> tuple[ImuSamples, jax.Array]:
    """Interval ``i`` followed by ``i + 1`` compacted into one padded row (S,): the used
    samples of both in time order, then padding. Returns the row and whether it fitted."""
    S = samples.dt.shape[1]

    def pair(x):
        return jnp.concatenate([x[i], x[i + 1]], axis=0)

    dt, gyro, accel, mask = (pair(x) for x in (samples.dt, samples.gyro, samples.accel,
                                               samples.mask))
    # stable sort on "is padding": used samples first, each interval's order kept
    order = jnp.argsort(~mask, stable=True)[:S]
    fits = jnp.sum(mask) <= S
    return ImuSamples(dt[order], gyro[order], accel[order], mask[order]), fits


def drop_second_newest(state: WindowState, problem: WindowProblem, samples: ImuSamples,
                       noise: ImuNoise, params: CalibParams,
                       config: MarginalizeConfig = MarginalizeConfig()  # noqa: B008
                       ) -> tuple[WindowState, WindowProblem, ImuSamples]:
    """Remove frame ``n - 1`` (``n``: the newest used slot) and merge its IMU intervals.

    ``samples``: the raw samples the intervals were preintegrated from (``noise`` is the model
    they were preintegrated with; the merged interval's covariance shape, 9 or 15, follows
    the window's). ``params``: the rig used to carry a re-anchored landmark's depth over. The
    merged interval is flagged invalid (``pim.valid`` False, and its mask cleared) if the two
    intervals' samples exceed the per-interval capacity ``S``.

    The prior keeps its information but not the dropped frame: when it involves frame
    ``n - 1`` (it does once a marginalisation has happened: it then covers every older
    slot), that frame is marginalised out of the prior alone by Schur complement, as
    VINS-Mono's ``MARGIN_SECOND_NEW`` branch does with its ``drop_set``; the newest frame's
    columns move to slot ``n - 1`` with their linearisation point. The prior's constant term
    is not kept (it does not move the solution).

    Returns ``(state', problem', samples')`` with the newest frame moved to slot ``n - 1``.
    """
    return _drop_second_newest(state, problem, samples, noise, params, config)


def _prior_without(prior: Prior, k, src, keep, config: MarginalizeConfig) -> Prior:
    """``prior`` with slot ``k`` marginalised out and slot ``j`` then taking slot ``src[j]``
    (slots where ``keep`` is False emptied)."""
    N = src.shape[0]
    H = prior.J.T @ prior.J
    b = prior.J.T @ prior.r
    zero = jnp.zeros((), k.dtype)
    rows = jax.lax.dynamic_slice(H, (k * _D, zero), (_D, N * _D))
    Hkk = jax.lax.dynamic_slice(rows, (zero, k * _D), (_D, _D))
    bk = jax.lax.dynamic_slice(b, (k * _D,), (_D,))
    K = rows.T @ equilibrated_pinv(Hkk, config.pinv_eps)
    H = H - K @ rows
    b = b - K @ bk
    idx = (src[:, None] * _D + jnp.arange(_D)).reshape(-1)
    use = jnp.repeat(keep, _D)
    H = jnp.where(use[:, None] & use[None, :], H[idx][:, idx], 0.0)
    b = jnp.where(use, b[idx], 0.0)
    lin = jax.tree_util.tree_map(lambda x: x[src], prior.lin)
    out = equilibrated_prior(0.5 * (H + H.T), b, lin, config.prior_eps)
    return dataclasses.replace(out, mask=prior.mask)


@functools.partial(jax.jit, static_argnames=("config",))
def _drop_second_newest(state, problem, samples, noise, params, config):
    N = problem.frame_mask.shape[0]
    n = (jnp.sum(problem.frame_mask) - 1).astype(problem.landmarks.anchor.dtype)
    k = n - 1
    slots = jnp.arange(N)
    # frames: slot k takes slot n, slot n is freed
    src = jnp.where(slots >= k, jnp.minimum(slots + 1, N - 1), slots)
    frames = jax.tree_util.tree_map(lambda x: x[src], state.frames)
    frame_mask = problem.frame_mask & (slots < n)

    # IMU: interval k - 1 (k - 1 -> k) absorbs interval k (k -> n)
    merged, fits = _merge_samples(samples, k - 1)
    pim = problem.imu.pim
    first = jax.tree_util.tree_map(lambda x: x[k - 1], pim)
    # unrolled: the scan's per-step overhead, not its arithmetic, is the cost on XLA:CPU
    # (160 samples: 8.8 ms at unroll 1, 3.3 ms at 4, 5.7 ms at 8; the result does not change)
    new = preintegrate(merged.dt, merged.gyro, merged.accel, first.bias_gyro, first.bias_accel,
                       mask=merged.mask, noise=noise, scheme=pim.scheme,
                       bias_covariance=pim.cov.shape[-1] == 15, unroll=4)
    new = dataclasses.replace(new, valid=new.valid & fits)
    ivals = jnp.arange(N - 1)
    isrc = jnp.where(ivals >= k, jnp.minimum(ivals + 1, N - 2), ivals)

    def put(old, m):
        moved = old[isrc]
        return jnp.where((ivals == k - 1).reshape((-1,) + (1,) * m.ndim), m[None], moved)

    pim = jax.tree_util.tree_map(put, pim, new)
    i_mask = problem.imu.mask[isrc].at[k - 1].set(problem.imu.mask[k - 1]
                                                 & problem.imu.mask[k] & new.valid)
    i_mask = i_mask & (ivals < n - 1)
    new_samples = jax.tree_util.tree_map(put, samples, merged)
    new_samples = dataclasses.replace(new_samples,
                                      mask=new_samples.mask & (ivals < n - 1)[:, None])

    # landmarks anchored in the dropped frame: re-anchor in the newest frame's camera 0
    obs, lm = problem.observations, problem.landmarks
    L, M = lm.mask.shape[0], obs.mask.shape[0]
    om = obs.mask
    cand = om & (obs.frame == n) & (obs.camera == 0) & (lm.anchor[obs.landmark] == k)
    # the first such observation of each landmark (M when none)
    first_obs = jax.ops.segment_min(jnp.where(cand, jnp.arange(M), M), obs.landmark,
                                    num_segments=L)
    has = first_obs < M
    idx = jnp.minimum(first_obs, M - 1)
    moved = lm.mask & (lm.anchor == k)
    fr = state.frames
    P_a = jnp.concatenate([lm.bearing, jnp.ones((L, 1), lm.bearing.dtype)], -1)
    P_a = P_a / state.inv_depth[:, None]
    R_a, p_a = fr.rotation[lm.anchor], fr.position[lm.anchor]
    P_w = jnp.einsum("lij,lj->li", R_a, P_a @ params.R_BC[0].T + params.t_BC[0]) + p_a
    P_b = jnp.einsum("ij,lj->li", fr.rotation[n].T, P_w - fr.position[n])
    P_c = (P_b - params.t_BC[0]) @ params.R_BC[0]
    z = P_c[:, 2]
    ok = has & (z > problem.config.min_depth)
    inv_depth = jnp.where(moved & ok, 1.0 / jnp.where(ok, z, 1.0), state.inv_depth)
    bearing = jnp.where((moved & ok)[:, None], obs.xy[idx], lm.bearing)
    lm_mask = lm.mask & (~moved | ok)
    anchor = jnp.where(moved, n, lm.anchor)
    anchor = jnp.where(anchor >= n, anchor - 1, anchor)
    is_new_anchor = (moved & has)[obs.landmark] & (jnp.arange(M) == idx[obs.landmark])
    o_mask = om & (obs.frame != k) & ~is_new_anchor & lm_mask[obs.landmark]
    o_frame = jnp.where(obs.frame >= n, obs.frame - 1, obs.frame)

    new_problem = dataclasses.replace(
        problem, frame_mask=frame_mask,
        landmarks=Landmarks(anchor, bearing, lm_mask),
        observations=Observations(o_frame, obs.landmark, obs.camera, obs.xy, o_mask),
        imu=ImuFactors(pim, i_mask),
        prior=_prior_without(problem.prior, k, src, slots < n, config))
    return WindowState(frames, inv_depth), new_problem, new_samples
