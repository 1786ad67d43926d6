"""Configuration of the window cost and of the structured solver (frozen, hashable: they are
static pytree metadata, so a jitted solve compiles once per configuration)."""

from __future__ import annotations

import dataclasses

from uavcal_jax.data.euroc_rig import EUROC_CAM0_INTRINSICS

__all__ = ["ROBUST_KERNELS", "CostConfig", "SolverConfig"]

#: Robust functions of the reprojection residual (see :mod:`uavcal_jax.vio.robust`).
ROBUST_KERNELS = ("huber", "cauchy", "none")


@dataclasses.dataclass(frozen=True)
class CostConfig:
    """The window cost (RPEOD eqs. 7-9).

    Attributes:
        pixel_sigma: standard deviation of a feature position, pixels (VINS-Fusion: 1.5).
        focal_px: focal length that converts it to normalised coordinates,
            ``sigma / focal_px`` (VINS-Fusion's nominal ``FOCAL_LENGTH``; here EuRoC's cam0).
        robust: ``"huber"`` (RPEOD eq. 9, VINS-Mono's paper), ``"cauchy"`` (VINS-Fusion's
            code) or ``"none"``; applied to the squared whitened reprojection error.
        robust_scale: the kernel's scale in whitened units (sigmas); 1 in both references.
        imu_jitter: variance added to the IMU residual covariance's diagonal before
            whitening. Needed (e.g. 1e-12) when the bias random walks are zero: the bias rows
            then have zero covariance and would not whiten.
        min_depth: depths (m) in the observing camera below this are clamped when
            projecting, so a point crossing the image plane mid-iteration stays finite.
    """

    pixel_sigma: float = 1.5
    focal_px: float = float(EUROC_CAM0_INTRINSICS[0])
    robust: str = "huber"
    robust_scale: float = 1.0
    imu_jitter: float = 0.0
    min_depth: float = 1e-3

    def __post_init__(self):
        if self.robust not in ROBUST_KERNELS:
            raise ValueError(f"robust must be one of {ROBUST_KERNELS}, got {self.robust!r}")
        if not (self.pixel_sigma > 0 and self.focal_px > 0 and self.robust_scale > 0):
            raise ValueError("pixel_sigma, focal_px and robust_scale must be positive")

    @property
    def sqrt_info(self) -> float:
        """Whitening factor of a normalised-coordinate residual, ``focal_px / pixel_sigma``."""
        return self.focal_px / self.pixel_sigma


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """The structured Levenberg-Marquardt solve (:mod:`uavcal_jax.vio.solver`).

    The damped system is ``(H + lambda D) dx = -g`` with ``D = diag(H)`` (Marquardt's
    scaling, as Ceres), on frames and inverse depths alike.

    Attributes:
        max_iterations: iterations at most (a warm-started window needs a few).
        initial_damping: ``lambda`` at the first iteration; 0 with ``damping_factor`` 1 is
            plain Gauss-Newton.
        damping_factor: ``lambda`` is divided by it after an accepted step and multiplied by
            it after a rejected one.
        min_damping, max_damping: bounds of ``lambda``; the solve stops when it would exceed
            ``max_damping`` (no step decreases the cost).
        ftol: stop when an accepted step decreases the cost by less than ``ftol`` times it.
    """

    max_iterations: int = 10
    initial_damping: float = 1e-4
    damping_factor: float = 10.0
    min_damping: float = 1e-12
    max_damping: float = 1e8
    ftol: float = 1e-12
