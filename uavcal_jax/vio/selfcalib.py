"""Self-calibration of a constant IMU offset by descending through the VIO window solve.

The set-up: ``windows`` synthetic windows (:mod:`uavcal_jax.vio.synthetic`; different seeds,
the same closed-form flight, stereo landmarks) whose IMU samples all carry the same injected
constant offset ``o*`` (gyro rad/s, accel m/s^2 in the body frame). Each window's prior on
keyframe 0 pins its biases (sigmas 1e-3 rad/s, 1e-2 m/s^2), which is what separates a constant
offset from a per-window bias.

The estimate starts at ``o = 0``. The loss is the mean over the windows of the *converged*
window cost, ``L(o) = mean_k min_x f_k(x, o)``, each window re-solved from its previous solution
(warm start) at every evaluation. Its gradient comes from
:func:`~uavcal_jax.vio.implicit.solve_differentiable` (implicit differentiation; by the envelope
theorem it equals the partial derivative at the solution). Gyro and accel channels differ in
scale by ~100x in curvature, so plain gradient descent is preconditioned:
``o <- o - P^-1 grad L(o)`` with ``P`` the Hessian of ``L`` at the start, from forward
differences of the implicit gradient (six extra gradients per window, ``fd_step``),
symmetrised. ``method="newton"`` uses the full ``P``, updated by BFGS after each step (the loss
is only roughly quadratic in ``o``: the gyro offset tilts the gravity the accelerometer sees);
``"diag"`` its fixed diagonal only (per-channel scaling, slower where the channels are
correlated). Each step is ``lr`` times the preconditioned gradient, halved up to three times
until the loss decreases (the descent stops when it does not).

:func:`recover_offset` runs it; :func:`offset_errors` scores an estimate against the injected
truth per channel, per sensor and overall (channels divided by :data:`EUROC_BIAS_SCALE`).
``experiments/vio_selfcalib.py`` is the command-line study around it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data import euroc_rig
from uavcal_jax.vio.config import CostConfig, SolverConfig
from uavcal_jax.vio.implicit import solve_differentiable
from uavcal_jax.vio.marginalize import equilibrated_pinv, equilibrated_prior
from uavcal_jax.vio.residuals import window_cost
from uavcal_jax.vio.solver import StructuredSolver
from uavcal_jax.vio.synthetic import SyntheticConfig, SyntheticWindow, perturb, synthetic_window
from uavcal_jax.vio.window import FRAME_DIM, CalibParams, WindowProblem, WindowState

__all__ = ["DEFAULT_ACCEL", "DEFAULT_GYRO", "EUROC_BIAS_SCALE", "METHODS", "DescentConfig",
           "SelfCalibConfig", "descend_offset", "make_windows", "offset_errors",
           "pin_window_biases", "recover_offset"]

#: An injected offset of EuRoC ground-truth bias size (gyro rad/s, accel m/s^2): the study's
#: default.
DEFAULT_GYRO = (0.02, -0.03, 0.015)
DEFAULT_ACCEL = (0.1, -0.08, 0.12)
#: (6,) per-channel scales of the overall (scaled) error: EuRoC ground-truth bias norms
#: (0.08 rad/s, 0.16 m/s^2).
EUROC_BIAS_SCALE = np.repeat(euroc_rig.EUROC_BIAS_SCALE, 3)
#: :attr:`SelfCalibConfig.method` values.
METHODS = ("newton", "diag")
# pixel noise of the synthetic windows; the cost's sigma is sqrt(2) larger (an observation
# and its anchor are both noisy)
_PIXEL_SIGMA = 0.5


@dataclasses.dataclass(frozen=True)
class DescentConfig:
    """The preconditioned descent on the mean converged window cost (module docstring).

    Attributes:
        steps: descent steps after the Hessian estimate.
        method: ``"newton"`` (full preconditioner) or ``"diag"`` (its diagonal).
        lr: step size multiplying the preconditioned gradient.
        fd_step: (6,) forward-difference steps of the Hessian (rad/s, m/s^2).
        max_iterations: Levenberg-Marquardt iterations at most per solve.
        ftol: the solve's relative cost decrease to stop at: tight, since the envelope
            theorem behind the implicit gradient needs the converged minimum.
    """

    steps: int = 5
    method: str = "newton"
    lr: float = 1.0
    fd_step: tuple[float, ...] = (5e-3,) * 3 + (2e-2,) * 3
    max_iterations: int = 40
    ftol: float = 1e-12

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be 'newton' or 'diag', got {self.method!r}")


@dataclasses.dataclass(frozen=True)
class SelfCalibConfig:
    """One recovery run on synthetic windows.

    Attributes:
        windows: windows ``K`` sharing the offset.  seed: window ``k`` uses seed
            ``seed * 1000 + k`` (its warm start ``+ 500``).
        n_frames, n_landmarks, keyframe_dt: window size (keyframes, landmarks, seconds).
        descent: the descent's settings.
    """

    windows: int = 4
    seed: int = 0
    n_frames: int = 10
    n_landmarks: int = 120
    keyframe_dt: float = 0.15
    descent: DescentConfig = DescentConfig()


def _pad_observations(w: SyntheticWindow, M: int) -> SyntheticWindow:
    """``w`` with its observation slots padded (masked off) to ``M``, so every window has the
    same shapes and the solve compiles once."""
    obs = w.problem.observations
    pad = M - obs.mask.shape[0]
    if pad == 0:
        return w

    def grow(a):
        return jnp.concatenate([a, jnp.zeros((pad,) + a.shape[1:], a.dtype)])

    obs = jax.tree_util.tree_map(grow, obs)
    return dataclasses.replace(w, problem=dataclasses.replace(w.problem, observations=obs))


def make_windows(offset, cfg: SelfCalibConfig) -> list[SyntheticWindow]:
    """``cfg.windows`` synthetic windows whose IMU samples carry ``offset`` (6,), padded to one
    observation capacity. Call under ``jax.enable_x64(True)``."""
    cost = CostConfig(pixel_sigma=_PIXEL_SIGMA * np.sqrt(2.0))
    scfg = SyntheticConfig(n_frames=cfg.n_frames, n_landmarks=cfg.n_landmarks,
                           keyframe_dt=cfg.keyframe_dt, pixel_sigma=_PIXEL_SIGMA,
                           imu_offset=tuple(float(v) for v in offset))
    ws = [synthetic_window(scfg, seed=cfg.seed * 1000 + k, cost_config=cost)
          for k in range(cfg.windows)]
    M = max(int(w.problem.observations.mask.shape[0]) for w in ws)
    return [_pad_observations(w, M) for w in ws]


def offset_errors(injected, estimate) -> dict:
    """An offset estimate (6,) scored against the ``injected`` truth (6,); the start was zero.

    Returns ``err_before`` (= ``|injected|``) and ``err_after`` (6,) absolute errors,
    ``removed`` (6,) ``1 - err_after / err_before`` per channel (NaN where nothing was
    injected), ``removed_gyro``/``removed_accel`` (the same on 3-vector norms) and
    ``removed_scaled`` (on the 6-vector norm, channels divided by :data:`EUROC_BIAS_SCALE`).
    """
    injected = np.asarray(injected, np.float64)
    err_before = np.abs(injected)
    err_after = np.abs(np.asarray(estimate) - injected)
    with np.errstate(divide="ignore", invalid="ignore"):
        removed = np.where(err_before > 0, 1.0 - err_after / err_before, np.nan)

    def frac(sel, scale=1.0):
        before = np.linalg.norm(err_before[sel] / scale)
        return float(1.0 - np.linalg.norm(err_after[sel] / scale) / before) if before else (
            float("nan"))

    return {"err_before": err_before, "err_after": err_after, "removed": removed,
            "removed_gyro": frac(slice(0, 3)), "removed_accel": frac(slice(3, 6)),
            "removed_scaled": frac(slice(0, 6), EUROC_BIAS_SCALE)}


def pin_window_biases(state: WindowState, problem: WindowProblem, sigma_gyro: float = 1e-4,
                      sigma_accel: float = 1e-3, eps: float = 1e-10
                      ) -> tuple[WindowState, WindowProblem]:
    """A window the VIO built (:attr:`~uavcal_jax.vio.estimator.StereoVio.window_sink`),
    made to carry a constant IMU offset in :class:`CalibParams` instead of in its bias states.

    Within one window an offset and a bias change are the same thing; the VIO's bias states
    absorb both. Here the bias information is marginalised out of the window's prior (the
    Schur complement of its bias block, so what the old frames said about the poses and
    velocities stays), and every keyframe in use gets a zero-mean prior on its biases of
    ``sigma_gyro`` rad/s and ``sigma_accel`` m/s^2: the window's IMU then reads ``0 + offset``
    where it read the bias (through the first-order bias correction about the biases it was
    integrated at, the VIO's estimates, which are near the total constant error). Keyframes
    the old prior said nothing about are linearised at ``state`` (a finite point for their
    pins; nothing else changes). Returns the state with zero biases (the pinned solve's start)
    and the problem. Host-side (NumPy float64), once per window; call under
    ``jax.enable_x64(True)``.
    """
    prior = problem.prior
    used = np.asarray(problem.frame_mask, bool)
    n = used.shape[0]
    dim = FRAME_DIM * n
    J = np.asarray(prior.J, np.float64) if bool(prior.mask) else np.zeros((dim, dim))
    r = np.asarray(prior.r, np.float64) if bool(prior.mask) else np.zeros(dim)
    H, b = J.T @ J, J.T @ r  # information form: 0.5 d^T H d + b^T d
    index = np.arange(dim).reshape(n, FRAME_DIM)
    bias, rest = index[:, 9:].ravel(), index[:, :9].ravel()
    gain = H[np.ix_(rest, bias)] @ np.asarray(
        equilibrated_pinv(jnp.asarray(H[np.ix_(bias, bias)]), eps))
    H_new, b_new = np.zeros((dim, dim)), np.zeros(dim)
    H_new[np.ix_(rest, rest)] = H[np.ix_(rest, rest)] - gain @ H[np.ix_(bias, rest)]
    b_new[rest] = b[rest] - gain @ b[bias]

    informed = np.any(J != 0.0, axis=0).reshape(n, FRAME_DIM).any(axis=1)

    def pick(lin, current):
        keep = informed.reshape((n,) + (1,) * (np.ndim(lin) - 1))
        return jnp.asarray(np.where(keep, np.asarray(lin), np.asarray(current)))

    lin = jax.tree_util.tree_map(pick, prior.lin, state.frames)
    weight = np.r_[np.full(3, sigma_gyro ** -2.0), np.full(3, sigma_accel ** -2.0)]
    lin_bias = np.concatenate([np.asarray(lin.bias_gyro), np.asarray(lin.bias_accel)], axis=1)
    for f in np.flatnonzero(used):
        pins = index[f, 9:]
        H_new[pins, pins] += weight  # 0.5 w (b_lin + d)^2
        b_new[pins] += weight * lin_bias[f]
    pinned = equilibrated_prior(jnp.asarray(H_new), jnp.asarray(b_new), lin, eps)
    pinned = dataclasses.replace(pinned, mask=jnp.asarray(True))
    frames = dataclasses.replace(state.frames,
                                 bias_gyro=jnp.zeros_like(state.frames.bias_gyro),
                                 bias_accel=jnp.zeros_like(state.frames.bias_accel))
    return (dataclasses.replace(state, frames=frames),
            dataclasses.replace(problem, prior=pinned))


def _loss_and_gradient(solver: StructuredSolver, problems: list[WindowProblem],
                       params: list[CalibParams]):
    """``loss_grad(o, xs) -> (mean converged cost, its gradient (6,), the solutions)``, each
    window solved from its warm start in ``xs``."""

    def cost(o, x, problem, p):
        p = dataclasses.replace(p, imu_offset=o)
        xs, _ = solve_differentiable(solver, x, problem, p)
        return window_cost(xs, problem, p), xs

    # outside jit: the solver's and the backward rule's executables are compiled once
    value_and_grad = jax.value_and_grad(cost, has_aux=True)

    def loss_grad(o, xs):
        vals, grads, sols = [], [], []
        for x, problem, p in zip(xs, problems, params, strict=True):
            (v, s), g = value_and_grad(jnp.asarray(o), x, problem, p)
            vals.append(float(v))
            grads.append(np.asarray(g))
            sols.append(s)
        return float(np.mean(vals)), np.mean(grads, 0), sols

    return loss_grad


def descend_offset(problems: list[WindowProblem], params: list[CalibParams],
                   starts: list[WindowState], cfg: DescentConfig = DescentConfig(),
                   log: Callable[[str], None] | None = None) -> dict:
    """The constant IMU offset (6,) (gyro rad/s, accel m/s^2) shared by ``problems``, from
    ``o = 0`` by preconditioned descent on their mean converged cost (module docstring).

    Args:
        problems: windows of equal capacities (one compilation), whose prior separates a
            constant offset from the bias states (a pin on the biases).
        params: each window's rig; its ``imu_offset`` is replaced by the estimate.
        starts: each window's warm start.
        cfg: the descent's settings.  log: receives one line per stage.

    Returns a dict: ``estimate`` (6,), ``sigma`` (6,) Cramer-Rao-like standard deviation from
    the Hessian (``L`` is half a chi-square per window, so the information of all ``K``
    windows is ``K P``), ``loss`` (steps + 1,) history, ``estimates``, ``hessian`` (6, 6) and
    its ``hessian_eigenvalues``, ``first_eval_s`` (the first evaluation, compilation
    included) and ``finite``: false (and the rest NaN) when a cost, gradient or Hessian was not
    finite (a solve that diverged). Call under ``jax.enable_x64(True)``.
    """
    log = log or (lambda _: None)
    solver = StructuredSolver(SolverConfig(max_iterations=cfg.max_iterations, ftol=cfg.ftol))
    loss_grad = _loss_and_gradient(solver, problems, params)

    o = np.zeros(6)
    p0 = [dataclasses.replace(p, imu_offset=jnp.zeros(6)) for p in params]
    # converged well (two solves) before the differences are taken: a partly converged
    # start would leak into the Hessian estimate
    xs = list(starts)
    for _ in range(2):
        xs = [solver(x, pr, p)[0] for x, pr, p in zip(xs, problems, p0, strict=True)]
    t = time.perf_counter()
    loss, g, xs = loss_grad(o, xs)
    first_s = time.perf_counter() - t
    log(f"start: loss {loss:.4f}  (first evaluation, compile included, {first_s:.1f} s)")
    if not (np.isfinite(loss) and np.all(np.isfinite(g))):
        return _no_estimate(loss, first_s)

    # Hessian of the reduced loss by forward differences of the implicit gradient; the
    # loss is near-quadratic in o, so one estimate at the start serves every step
    h = np.asarray(cfg.fd_step, np.float64)
    P = np.zeros((6, 6))
    for i in range(6):
        _, g_i, _ = loss_grad(o + h[i] * np.eye(6)[i], xs)
        P[:, i] = (g_i - g) / h[i]
    P = 0.5 * (P + P.T)
    if not np.all(np.isfinite(P)):
        return _no_estimate(loss, first_s)
    eig = np.linalg.eigvalsh(P)
    log(f"Hessian eigenvalues {np.array2string(eig, precision=3)}")
    # diag, or a Hessian that differences left indefinite: per-channel scaling only
    full = cfg.method == "newton" and eig.min() > 0
    precond = P if full else np.diag(np.abs(np.diag(P)))
    sigma = np.sqrt(np.diag(np.linalg.inv(len(problems) * P))) if eig.min() > 0 else (
        np.full(6, np.nan))

    losses, estimates = [loss], [o.copy()]
    for step in range(cfg.steps):
        d = -cfg.lr * np.linalg.solve(precond, g)
        # backtracking: the loss is only near-quadratic, so a full step may overshoot
        for _ in range(4):
            o_new = o + d
            loss_new, g_new, xs_new = loss_grad(o_new, xs)
            if loss_new < loss:
                break
            d = 0.5 * d
        if loss_new >= loss:
            break
        # BFGS update of the preconditioner with the step and the gradient change
        s_k, y_k = o_new - o, g_new - g
        if cfg.method == "newton" and s_k @ y_k > 0:
            Ps = precond @ s_k
            precond = precond - np.outer(Ps, Ps) / (s_k @ Ps) + np.outer(y_k, y_k) / (
                s_k @ y_k)
        o, loss, g, xs = o_new, loss_new, g_new, xs_new
        losses.append(loss)
        estimates.append(o.copy())
        log(f"step {step + 1}: loss {loss:.4f}  |grad| {np.linalg.norm(g):.3g}  "
            f"o {np.array2string(o, precision=4)}")
    return {"estimate": o, "sigma": sigma, "loss": np.asarray(losses),
            "estimates": np.asarray(estimates), "hessian": P, "hessian_eigenvalues": eig,
            "first_eval_s": first_s, "finite": True}


def _no_estimate(loss: float, first_s: float) -> dict:
    """:func:`descend_offset`'s answer when a window's cost, gradient or Hessian is not
    finite (a solve that diverged): NaN estimate, ``finite`` false."""
    nan6 = np.full(6, np.nan)
    return {"estimate": nan6, "sigma": nan6, "loss": np.array([loss]),
            "estimates": nan6[None], "hessian": np.full((6, 6), np.nan),
            "hessian_eigenvalues": nan6, "first_eval_s": first_s, "finite": False}


def recover_offset(offset, cfg: SelfCalibConfig = SelfCalibConfig(),
                   log: Callable[[str], None] | None = None) -> dict:
    """Estimate the constant IMU offset injected as ``offset`` (6,) (gyro rad/s, accel m/s^2)
    into ``cfg.windows`` synthetic windows, by :func:`descend_offset` from ``o = 0``. ``log``:
    receives one line per stage (nothing is printed).

    Returns :func:`descend_offset`'s dict with ``injected``, the keys of :func:`offset_errors`,
    the run's settings and timings (s). Runs under ``jax.enable_x64(True)`` itself.
    """
    injected = np.asarray(offset, np.float64)
    t_start = time.perf_counter()
    with jax.enable_x64(True):
        ws = make_windows(injected, cfg)
        build_s = time.perf_counter() - t_start
        # the warm starts: perturbed truths
        starts = [perturb(w.truth, seed=cfg.seed * 1000 + 500 + k) for k, w in enumerate(ws)]
        res = descend_offset([w.problem for w in ws], [w.params for w in ws], starts,
                             cfg.descent, log)
    wall_s = time.perf_counter() - t_start
    return {
        "injected": injected, **res, **offset_errors(injected, res["estimate"]),
        "method": cfg.descent.method, "windows": cfg.windows, "seed": cfg.seed,
        "observations": int(ws[0].problem.observations.mask.shape[0]),
        "build_s": build_s, "wall_s": wall_s,
    }
