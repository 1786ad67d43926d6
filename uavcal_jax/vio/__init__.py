"""Stereo visual-inertial odometry (RPEOD sec. 3.1-3.3; VINS-Fusion's design).

Modules, one job each. Settings:

* :mod:`~uavcal_jax.vio.config`: every setting, one tree (:class:`VioConfig`: front end,
  keyframes, cost, solver, marginalisation, failure limits, initial prior) and
  :func:`resolve_camera`, which fills the camera-dependent values from the recording.

Front end (OpenCV, NumPy):

* :mod:`~uavcal_jax.vio.frontend`: Shi-Tomasi corners, pyramidal Lucas-Kanade with a
  forward-backward check, outlier rejection on undistorted points, left-to-right stereo
  matches.
* :mod:`~uavcal_jax.vio.keyframes`: the keyframe decision on gyro-compensated parallax.

Back end (JAX, pure functions):

* :mod:`~uavcal_jax.vio.window`: the sliding-window pytrees (fixed capacities, masks) and the
  retraction ``x ⊞ delta``.
* :mod:`~uavcal_jax.vio.robust`: Huber / Cauchy functions of the squared residual.
* :mod:`~uavcal_jax.vio.residuals`: reprojection, IMU and prior residuals; ``window_cost``.
* :mod:`~uavcal_jax.vio.normal`: the structured normal equations and their Schur solve.
* :mod:`~uavcal_jax.vio.solver`: the :class:`Solver` interface and the structured
  Levenberg-Marquardt; :mod:`~uavcal_jax.vio.reference`: jaxopt behind the same interface.
* :mod:`~uavcal_jax.vio.marginalize`: sliding the window (the oldest keyframe marginalised
  into a linear prior, or the second-newest frame dropped with its IMU intervals merged).
* :mod:`~uavcal_jax.vio.implicit`: gradients of the solution by implicit differentiation.
* :mod:`~uavcal_jax.vio.synthetic`: an exactly consistent synthetic window.

Evaluation: :mod:`~uavcal_jax.vio.trajectory_metrics` (ATE and RPE with evo's alignment; the
trajectory plot is :func:`uavcal_jax.plots.plot_trajectories`).

Everything is float64 under ``jax.enable_x64(True)``.
"""

from uavcal_jax.vio.config import (
    CostConfig,
    FailureLimits,
    FrontendConfig,
    InitialPrior,
    KeyframeConfig,
    MarginalizeConfig,
    SolverConfig,
    VioConfig,
    resolve_camera,
)
from uavcal_jax.vio.frontend import FeatureTracker, FrameFeatures
from uavcal_jax.vio.implicit import solve_differentiable
from uavcal_jax.vio.keyframes import KeyframeDecision, body_to_camera_rotation, keyframe_decision
from uavcal_jax.vio.marginalize import (
    drop_second_newest,
    marginal_information,
    marginalize_oldest,
    slide_imu_samples,
)
from uavcal_jax.vio.normal import NormalEquations, normal_equations
from uavcal_jax.vio.reference import JaxoptSolver
from uavcal_jax.vio.residuals import (
    factor_residuals,
    flat_residual,
    window_cost,
)
from uavcal_jax.vio.solver import (
    SolveInfo,
    Solver,
    StructuredSolver,
    gauss_newton_step,
    structured_solve,
)
from uavcal_jax.vio.trajectory_metrics import (
    AteResult,
    RpeResult,
    ate,
    rpe,
    trajectory_errors,
)
from uavcal_jax.vio.window import (
    CalibParams,
    ImuFactors,
    ImuSamples,
    Keyframes,
    Landmarks,
    Observations,
    Prior,
    WindowProblem,
    WindowState,
    frame_difference,
    prior_from_information,
    retract,
)

__all__ = [
    "AteResult",
    "FeatureTracker",
    "FrameFeatures",
    "FrontendConfig",
    "KeyframeConfig",
    "KeyframeDecision",
    "RpeResult",
    "ate",
    "body_to_camera_rotation",
    "keyframe_decision",
    "rpe",
    "trajectory_errors",
    "CalibParams",
    "CostConfig",
    "FailureLimits",
    "InitialPrior",
    "ImuFactors",
    "ImuSamples",
    "JaxoptSolver",
    "Keyframes",
    "Landmarks",
    "MarginalizeConfig",
    "NormalEquations",
    "Observations",
    "Prior",
    "SolveInfo",
    "Solver",
    "SolverConfig",
    "StructuredSolver",
    "VioConfig",
    "WindowProblem",
    "WindowState",
    "drop_second_newest",
    "flat_residual",
    "frame_difference",
    "gauss_newton_step",
    "marginal_information",
    "marginalize_oldest",
    "normal_equations",
    "prior_from_information",
    "factor_residuals",
    "resolve_camera",
    "retract",
    "slide_imu_samples",
    "solve_differentiable",
    "structured_solve",
    "window_cost",
]
