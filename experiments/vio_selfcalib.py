"""Self-calibration of a constant IMU offset by descending through the VIO window solve.

The set-up: ``--windows`` synthetic windows (:mod:`uavcal_jax.vio.synthetic`; different seeds,
the same closed-form flight, stereo landmarks) whose IMU samples all carry the same injected
constant offset ``o*`` (gyro rad/s, accel m/s^2 in the body frame; the defaults are of the size
of EuRoC's ground-truth biases, about 0.08 rad/s and 0.16 m/s^2 in norm). Each window's prior
on keyframe 0 pins its biases (sigmas 1e-3 rad/s, 1e-2 m/s^2), which is what separates a
constant offset from a per-window bias.

The estimate starts at ``o = 0``. The loss is the mean over the windows of the *converged*
window cost, ``L(o) = mean_k min_x f_k(x, o)``, each window re-solved from its previous solution
(warm start) at every evaluation. Its gradient comes from
:func:`uavcal_jax.vio.solve_differentiable` (implicit differentiation; by the envelope theorem
it equals the partial derivative at the solution). Gyro and accel channels differ in scale by
~100x in curvature, so plain gradient descent is preconditioned: ``o <- o - P^-1 grad L(o)``
with ``P`` the Hessian of ``L`` at the start, from forward differences of the implicit
gradient (six extra gradients per window, ``--fd-step``), symmetrised. ``--method newton``
(default) uses the full ``P``, updated by BFGS after each step (the loss is only roughly
quadratic in ``o``: the gyro offset tilts the gravity the accelerometer sees); ``--method diag``
its fixed diagonal only (per-channel scaling, slower where the channels are correlated). Each
step is ``--lr`` times the preconditioned gradient, halved up to three times until the loss
decreases (the descent stops when it does not).

Reported per channel: the injected offset, the estimate, ``|error|`` before (``= |o*|``, the
start is zero) and after, and the fraction removed ``1 - |err_after| / |err_before|``; per
sensor (3-vector norms) and overall in a scaled sense: each channel divided by its sensor's
EuRoC bias scale (0.08 rad/s, 0.16 m/s^2) before the 6-vector norm is taken. Also the
Cramer-Rao-like standard deviation of the estimate from the Hessian (``L`` is half a chi-square
per window, so the information of all windows is ``K P``).

Prints a markdown table and, as the last line, one JSON object. The default run takes a few
minutes on a 2-core CPU, most of it compiling the solve and its backward rule once.

Usage::

    python experiments/vio_selfcalib.py
    python experiments/vio_selfcalib.py --windows 6 --steps 4 --seeds 2
    python experiments/vio_selfcalib.py --gyro=-0.05,0.02,0.03 --accel 0.1,0.1,-0.1
    python experiments/vio_selfcalib.py --large     # larger windows, more of them
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.argtypes import positive, positive_int, print_json
from uavcal_jax.vio import (
    CostConfig,
    SolverConfig,
    StructuredSolver,
    solve_differentiable,
    window_cost,
)
from uavcal_jax.vio.synthetic import SyntheticConfig, SyntheticWindow, perturb, synthetic_window

#: Injected offsets of the issue (gyro rad/s, accel m/s^2), EuRoC-bias sized.
DEFAULT_GYRO = (0.02, -0.03, 0.015)
DEFAULT_ACCEL = (0.1, -0.08, 0.12)
#: Per-sensor scales of the overall (scaled) error: EuRoC ground-truth bias norms.
EUROC_BIAS_SCALE = np.repeat([0.08, 0.16], 3)
CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")
PIXEL_SIGMA = 0.5


@dataclasses.dataclass(frozen=True)
class SelfCalibConfig:
    """One recovery run.

    Attributes:
        windows: windows ``K`` sharing the offset.  seed: window ``k`` uses seed
            ``seed * 1000 + k`` (its warm start ``+ 500``).
        n_frames, n_landmarks, keyframe_dt: window size (keyframes, landmarks, seconds).
        steps: descent steps after the Hessian estimate.
        method: ``"newton"`` (full preconditioner) or ``"diag"`` (its diagonal).
        lr: step size multiplying the preconditioned gradient.
        fd_step: (6,) forward-difference steps of the Hessian (rad/s, m/s^2).
        max_iterations: Levenberg-Marquardt iterations at most per solve.
    """

    windows: int = 4
    seed: int = 0
    n_frames: int = 10
    n_landmarks: int = 120
    keyframe_dt: float = 0.15
    steps: int = 5
    method: str = "newton"
    lr: float = 1.0
    fd_step: tuple[float, ...] = (5e-3,) * 3 + (2e-2,) * 3
    max_iterations: int = 40


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
    cost = CostConfig(pixel_sigma=PIXEL_SIGMA * np.sqrt(2.0))
    scfg = SyntheticConfig(n_frames=cfg.n_frames, n_landmarks=cfg.n_landmarks,
                           keyframe_dt=cfg.keyframe_dt, pixel_sigma=PIXEL_SIGMA,
                           imu_offset=tuple(float(v) for v in offset))
    ws = [synthetic_window(scfg, seed=cfg.seed * 1000 + k, cost_config=cost)
          for k in range(cfg.windows)]
    M = max(int(w.problem.observations.mask.shape[0]) for w in ws)
    return [_pad_observations(w, M) for w in ws]


def recover_offset(offset, cfg: SelfCalibConfig = SelfCalibConfig(),
                   log: Callable[[str], None] | None = None) -> dict:
    """Estimate the constant IMU offset injected as ``offset`` (6,) (gyro rad/s, accel m/s^2)
    from ``o = 0`` by preconditioned descent on the mean converged window cost.

    Returns a dict: ``injected``, ``estimate``, ``err_before``, ``err_after`` (6,) absolute
    errors, ``removed`` (6,) per channel, ``removed_gyro``/``removed_accel`` (3-vector norms),
    ``removed_scaled`` (overall, channels divided by :data:`EUROC_BIAS_SCALE`), ``sigma`` (6,)
    standard deviation of the estimate from the Hessian, ``loss`` (steps + 1,) history,
    ``hessian`` (6, 6), timings. Runs under ``jax.enable_x64(True)`` itself.
    """
    log = log or (lambda _: None)
    injected = np.asarray(offset, np.float64)
    if cfg.method not in ("newton", "diag"):
        raise ValueError(f"method must be 'newton' or 'diag', got {cfg.method!r}")
    t_start = time.perf_counter()
    with jax.enable_x64(True):
        ws = make_windows(injected, cfg)
        build_s = time.perf_counter() - t_start
        solver = StructuredSolver(SolverConfig(max_iterations=cfg.max_iterations))

        def cost(o, x, w):
            params = dataclasses.replace(w.params, imu_offset=o)
            xs, _ = solve_differentiable(solver, x, w.problem, params)
            return window_cost(xs, w.problem, params), xs

        # outside jit: the solver's and the backward rule's executables are compiled once
        value_and_grad = jax.value_and_grad(cost, has_aux=True)

        def loss_grad(o, xs):
            """Mean converged cost, its gradient (6,) and the solutions (warm starts)."""
            vals, grads, sols = [], [], []
            for x, w in zip(xs, ws, strict=True):
                (v, s), g = value_and_grad(jnp.asarray(o), x, w)
                vals.append(float(v))
                grads.append(np.asarray(g))
                sols.append(s)
            return float(np.mean(vals)), np.mean(grads, 0), sols

        o = np.zeros(6)
        # the warm starts: perturbed truths solved at the starting estimate
        xs = [perturb(w.truth, seed=cfg.seed * 1000 + 500 + k) for k, w in enumerate(ws)]
        p0 = [dataclasses.replace(w.params, imu_offset=jnp.zeros(6)) for w in ws]
        # converged well (two solves) before the differences are taken: a partly converged
        # start would leak into the Hessian estimate
        for _ in range(2):
            xs = [solver(x, w.problem, p)[0] for x, w, p in zip(xs, ws, p0, strict=True)]
        t = time.perf_counter()
        loss, g, xs = loss_grad(o, xs)
        first_s = time.perf_counter() - t
        log(f"start: loss {loss:.4f}  (first evaluation, compile included, {first_s:.1f} s)")

        # Hessian of the reduced loss by forward differences of the implicit gradient; the
        # loss is near-quadratic in o, so one estimate at the start serves every step
        h = np.asarray(cfg.fd_step, np.float64)
        P = np.zeros((6, 6))
        for i in range(6):
            _, g_i, _ = loss_grad(o + h[i] * np.eye(6)[i], xs)
            P[:, i] = (g_i - g) / h[i]
        P = 0.5 * (P + P.T)
        eig = np.linalg.eigvalsh(P)
        log(f"Hessian eigenvalues {np.array2string(eig, precision=3)}")
        # diag, or a Hessian that differences left indefinite: per-channel scaling only
        full = cfg.method == "newton" and eig.min() > 0
        precond = P if full else np.diag(np.abs(np.diag(P)))
        sigma = np.sqrt(np.diag(np.linalg.inv(cfg.windows * P))) if eig.min() > 0 else (
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
    wall_s = time.perf_counter() - t_start

    err_before = np.abs(injected)
    err_after = np.abs(o - injected)
    with np.errstate(divide="ignore", invalid="ignore"):
        removed = np.where(err_before > 0, 1.0 - err_after / err_before, np.nan)

    def frac(sel, scale=1.0):
        before = np.linalg.norm(err_before[sel] / scale)
        return float(1.0 - np.linalg.norm(err_after[sel] / scale) / before) if before else (
            float("nan"))

    return {
        "injected": injected, "estimate": o, "err_before": err_before, "err_after": err_after,
        "removed": removed, "removed_gyro": frac(slice(0, 3)),
        "removed_accel": frac(slice(3, 6)),
        "removed_scaled": frac(slice(0, 6), EUROC_BIAS_SCALE),
        "sigma": sigma, "loss": np.asarray(losses), "estimates": np.asarray(estimates),
        "hessian": P, "hessian_eigenvalues": eig, "method": cfg.method,
        "windows": cfg.windows, "seed": cfg.seed,
        "observations": int(ws[0].problem.observations.mask.shape[0]),
        "build_s": build_s, "first_eval_s": first_s, "wall_s": wall_s,
    }


def markdown_table(result: dict) -> str:
    """Per-channel table of one run (units: rad/s for g*, m/s^2 for a*)."""
    lines = ["| channel | injected | estimate | abs err before | abs err after | removed "
             "| sigma |", "|---|---|---|---|---|---|---|"]
    for i, name in enumerate(CHANNELS):
        lines.append(
            f"| {name} | {result['injected'][i]:+.4f} | {result['estimate'][i]:+.4f} "
            f"| {result['err_before'][i]:.4f} | {result['err_after'][i]:.2e} "
            f"| {100 * result['removed'][i]:.1f} % | {result['sigma'][i]:.1e} |")
    lines.append(
        f"\nremoved: gyro (norm) {100 * result['removed_gyro']:.1f} %, accel (norm) "
        f"{100 * result['removed_accel']:.1f} %, overall (channels / EuRoC bias scale "
        f"0.08 rad/s, 0.16 m/s^2) {100 * result['removed_scaled']:.1f} %; loss "
        f"{result['loss'][0]:.3f} -> {result['loss'][-1]:.3f}")
    return "\n".join(lines)


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z, got {text!r}")
    values = tuple(float(v) for v in parts)
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gyro", type=_triple, default=DEFAULT_GYRO,
                    help="injected gyro offset GX,GY,GZ rad/s (negative first value: "
                         "--gyro=-0.01,...) [default: 0.02,-0.03,0.015]")
    ap.add_argument("--accel", type=_triple, default=DEFAULT_ACCEL,
                    help="injected accel offset AX,AY,AZ m/s^2 [default: 0.1,-0.08,0.12]")
    ap.add_argument("--windows", type=positive_int, default=None,
                    help="windows sharing the offset [default: 4; --large: 8]")
    ap.add_argument("--seeds", type=positive_int, default=1,
                    help="independent runs (new windows each) [default: 1]")
    ap.add_argument("--steps", type=positive_int, default=5, help="descent steps [default: 5]")
    ap.add_argument("--method", choices=("newton", "diag"), default="newton")
    ap.add_argument("--lr", type=positive, default=1.0)
    ap.add_argument("--frames", type=positive_int, default=10)
    ap.add_argument("--landmarks", type=positive_int, default=None,
                    help="landmarks per window [default: 120; --large: 300]")
    ap.add_argument("--keyframe-dt", type=positive, default=0.15)
    ap.add_argument("--large", action="store_true",
                    help="a larger problem than the few-minute default: 8 windows of 300 landmarks")
    args = ap.parse_args(argv)

    windows = args.windows or (8 if args.large else 4)
    landmarks = args.landmarks or (300 if args.large else 120)
    offset = np.array(args.gyro + args.accel)
    t = time.perf_counter()
    runs = []
    for seed in range(args.seeds):
        cfg = SelfCalibConfig(windows=windows, seed=seed, n_frames=args.frames,
                              n_landmarks=landmarks, keyframe_dt=args.keyframe_dt,
                              steps=args.steps, method=args.method, lr=args.lr)
        res = recover_offset(offset, cfg, log=lambda s: print(s, file=sys.stderr))
        print(f"\n### seed {seed}: {windows} windows x {args.frames} keyframes x {landmarks} "
              f"landmarks, {args.method}, {args.steps} steps, {res['wall_s']:.0f} s\n")
        print(markdown_table(res))
        runs.append(res)
    wall_s = time.perf_counter() - t

    keys = ("estimate", "err_after", "removed", "sigma", "loss")
    out = {
        "injected": offset, "windows": windows, "frames": args.frames, "landmarks": landmarks,
        "keyframe_dt": args.keyframe_dt, "steps": args.steps, "method": args.method,
        "seeds": args.seeds,
        "runs": [{k: r[k] for k in keys + ("removed_gyro", "removed_accel", "removed_scaled",
                                             "wall_s")} for r in runs],
        "removed_min_channel": float(np.min([r["removed"] for r in runs])),
        "removed_scaled_mean": float(np.mean([r["removed_scaled"] for r in runs])),
        "loss_decreased": bool(all(r["loss"][-1] < r["loss"][0] for r in runs)),
        "wall_s": round(wall_s, 1),
    }
    print()
    print_json(out)
    return out


if __name__ == "__main__":
    main()
