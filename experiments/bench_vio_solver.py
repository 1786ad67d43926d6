"""Benchmark the structured window solve against jaxopt on one full-size window.

The issue's set-up: one synthetic window of 10 keyframes and 300 landmarks (stereo and
temporal observations, about 7,500 residual rows; :mod:`uavcal_jax.vio.synthetic`), warm-started
from a perturbed truth. Timed, after a warm-up call (compile times reported apart):

* ``structured_step_ms``: median of one structured Gauss-Newton iteration
  (:func:`uavcal_jax.vio.gauss_newton_step`: assemble with per-block ``jacfwd`` and segment
  sums, Schur-eliminate the inverse depths, Cholesky on the 150x150 frame block,
  back-substitute, retract, evaluate the cost);
  ``structured_step_min_ms``: the fastest repeat (on a shared CPU the median swings by 10x);
* ``structured_solve_ms``: median of a whole :class:`~uavcal_jax.vio.StructuredSolver` solve
  (Levenberg-Marquardt, ``--iterations`` at most) and the iterations it ran;
* ``jaxopt_gn_solve_s``: median of ``jaxopt.GaussNewton`` (matrix-free CG inner solves) on the
  flattened residual of the same cost, ``--iterations`` outer iterations at most;
  ``--lm`` adds ``jaxopt.LevenbergMarquardt`` with a materialised Jacobian (slow).

The CPU is often shared; run it on a quiet machine for stable numbers. The last line printed
is one JSON object.

Usage::

    python experiments/bench_vio_solver.py
    python experiments/bench_vio_solver.py --repeats 5 --lm
"""

from __future__ import annotations

import argparse
import functools

import jax
import numpy as np
from _bench import time_calls, time_once  # the script's folder is first on sys.path
from _docs import add_write_docs, figures_table, write_docs

from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.vio import (
    JaxoptSolver,
    SolverConfig,
    StructuredSolver,
    gauss_newton_step,
    window_cost,
)
from uavcal_jax.vio.residuals import imu_mask, observation_mask
from uavcal_jax.vio.synthetic import SyntheticConfig, perturb, synthetic_window


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=positive_int, default=10)
    ap.add_argument("--landmarks", type=positive_int, default=300)
    ap.add_argument("--iterations", type=positive_int, default=10,
                    help="outer iterations at most per solve (both solvers)")
    ap.add_argument("--repeats", type=positive_int, default=20,
                    help="timed repeats of the structured step (jaxopt: a fifth, at least 2)")
    ap.add_argument("--lm", action="store_true", help="also time jaxopt.LevenbergMarquardt")
    ap.add_argument("--seed", type=int, default=0)
    add_write_docs(ap)
    args = ap.parse_args(argv)

    with jax.enable_x64(True):
        w, build_s = time_once(lambda: synthetic_window(
            SyntheticConfig(n_frames=args.frames, n_landmarks=args.landmarks,
                            track_length=(4, args.frames)), seed=args.seed))
        x0 = perturb(w.truth, seed=args.seed + 1, rotation=2e-3, position=1e-2,
                     velocity=1e-2, inv_depth=0.05)
        p, q = w.problem, w.params
        rows = (2 * int(observation_mask(p).sum()) + 15 * int(imu_mask(p).sum())
                + 15 * args.frames)
        out = {"frames": args.frames, "landmarks": args.landmarks,
               "observations": int(observation_mask(p).sum()), "residual_rows": rows,
               "unknowns": 15 * args.frames + args.landmarks, "build_s": round(build_s, 2)}

        step = functools.partial(jax.jit(gauss_newton_step), x0, p, q)
        _, out["structured_step_compile_s"] = time_once(step)  # the first call compiles
        times = time_calls(step, repeats=args.repeats)
        out["structured_step_ms"] = 1e3 * times.median_s
        out["structured_step_min_ms"] = 1e3 * times.min_s

        solver = functools.partial(
            StructuredSolver(SolverConfig(max_iterations=args.iterations, ftol=1e-12)), x0, p, q)
        (x, info), out["structured_solve_compile_s"] = time_once(solver)
        out["structured_solve_ms"] = 1e3 * time_calls(solver, repeats=args.repeats).median_s
        out["structured_iterations"] = int(info.iterations)
        out["structured_cost"] = float(info.cost_final)

        slow_repeats = max(2, args.repeats // 5)
        gn = functools.partial(JaxoptSolver("gauss_newton", maxiter=args.iterations, tol=1e-10),
                               x0, p, q)
        (xg, ginfo), out["jaxopt_gn_compile_s"] = time_once(gn)
        out["jaxopt_gn_solve_s"] = time_calls(gn, repeats=slow_repeats).median_s
        out["jaxopt_gn_iterations"] = int(ginfo.iterations)
        out["jaxopt_gn_cost"] = float(window_cost(xg, p, q))
        if args.lm:
            lm = functools.partial(
                JaxoptSolver("levenberg_marquardt", maxiter=args.iterations, tol=1e-10),
                x0, p, q)
            (xl, linfo), out["jaxopt_lm_compile_s"] = time_once(lm)
            out["jaxopt_lm_solve_s"] = time_calls(lm, repeats=slow_repeats).median_s
            out["jaxopt_lm_iterations"] = int(linfo.iterations)
            out["jaxopt_lm_cost"] = float(window_cost(xl, p, q))
        out["speedup_step_vs_jaxopt_gn_solve"] = (
            out["jaxopt_gn_solve_s"] / (1e-3 * out["structured_step_ms"]))
        out["max_abs_position_diff_vs_jaxopt_gn"] = float(
            np.abs(np.asarray(x.frames.position - xg.frames.position)).max())
    for k, v in out.items():
        print(f"{k:36s} {v:.4g}" if isinstance(v, float) else f"{k:36s} {v}")
    write_docs(args, "bench_vio_solver", figures_table(out), argv=argv,
               anchor="jaxopt.GaussNewton on the same window, in the same run")
    print_json({k: (float(f"{v:.6g}") if isinstance(v, float) else v) for k, v in out.items()})
    return out


if __name__ == "__main__":
    main()
