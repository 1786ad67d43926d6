"""The gyro bias the camera's relative rotations imply: the ``visual-ls`` estimator.

An estimator of the gyroscope's constant error that needs no ground truth (VINS-Mono's
``solveGyroscopeBias``, run over a whole recording instead of an initialisation window), from
the body-frame rotations between frames that the front end's tracks give
(:mod:`uavcal_jax.vio.visual_rotation`, which has the measured reasons for its fits):

1. :func:`gyro_bias_least_squares` preintegrates the gyro over each interval
   (:func:`uavcal_jax.imu.preintegrate`, every sample) and solves for the bias that aligns the
   preintegrated rotations with the visual ones
   (:func:`uavcal_jax.vio.initialize.gyro_bias_from_relative_rotations`), by Gauss-Newton,
   re-preintegrating at each new bias, with intervals whose residual is more than
   ``outlier_mad`` MADs above the median dropped.
2. :func:`visual_gyro_bias` composes it with the rotations for a recording (cached beside it
   by :func:`~uavcal_jax.vio.rotation_cache.cached_relative_rotations`).

Only the gyro is observable this way: relative rotations carry no information about the
accelerometer (that needs the translation's metric scale and gravity, i.e. the full VIO).

Conventions: ``R[k]`` maps body-frame vectors at ``t1_ns[k]`` to the body frame at
``t0_ns[k]`` (``R_WB(t0)^T R_WB(t1)``), the convention of a preintegrated ``delta_R`` and of
the front end's ``R_prev_curr_gyro``. NumPy, float64; times int64 nanoseconds.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from uavcal_jax.data.sequence import ImuData, Sequence
from uavcal_jax.errors import DataError
from uavcal_jax.imu import interval_batch, preintegrate
from uavcal_jax.vio.config import FrontendConfig
from uavcal_jax.vio.initialize import gyro_bias_from_relative_rotations, rotation_residuals
from uavcal_jax.vio.rotation_cache import cached_relative_rotations
from uavcal_jax.vio.visual_rotation import (
    MIN_PARALLAX_PX,
    MIN_TRACKS,
    VisualRotations,
    relative_rotations,
)

__all__ = ["GyroBiasFit", "VisualGyroConfig", "gyro_bias_least_squares", "visual_gyro_bias"]


@dataclasses.dataclass(frozen=True)
class VisualGyroConfig:
    """The visual gyro-bias estimator (``visual-ls``).

    Attributes:
        frontend: the KLT tracker's settings; its ``ransac_threshold_px`` (at
            :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX`) is also the rotation fits'
            inlier threshold.
        every: frames per interval: pairs ``(0, every), (every, 2 every), ...``. A longer
            interval rotates more, so the bias (a rate) grows against the per-pair noise;
            tracks must survive it.
        min_tracks: fewest shared tracks (and inliers) for a pair to count.
        min_parallax_px: the median rotation-compensated parallax (pixels at the nominal
            focal) below which the translation is too small for the essential matrix, and the
            rotation-only fit is used.
        iterations: Gauss-Newton iterations of the bias (each re-preintegrates the gyro).
        outlier_mad: intervals whose residual norm exceeds the median by more than this many
            MADs (scaled to a standard deviation) are dropped.
    """

    frontend: FrontendConfig = FrontendConfig()
    every: int = 1
    min_tracks: int = MIN_TRACKS
    min_parallax_px: float = MIN_PARALLAX_PX
    iterations: int = 3
    outlier_mad: float = 5.0

    def __post_init__(self) -> None:
        if int(self.every) < 1 or int(self.min_tracks) < 8 or int(self.iterations) < 1:
            raise ValueError("every and iterations must be >= 1 and min_tracks >= 8, got "
                             f"{self.every}, {self.iterations}, {self.min_tracks}")
        if not (self.min_parallax_px >= 0 and self.outlier_mad > 0):
            raise ValueError("min_parallax_px must be >= 0 and outlier_mad > 0")



class GyroBiasFit(NamedTuple):
    """What :func:`gyro_bias_least_squares` found besides the bias.

    Attributes:
        bias_gyro: (3,) rad/s, the estimate (also returned on its own).
        cov: (3, 3) (rad/s)^2, its covariance from the residuals, treating them as i.i.d.
            per axis: ``sigma^2 (A^T A)^-1`` (``A`` the used intervals' bias Jacobians).
        residuals: (K,) x 3 rad, ``log(delta_R^T R_visual)`` at the final bias (NaN where the
            interval was not usable).
        per_interval: (K, 3) rad/s, the bias each used interval alone implies (NaN elsewhere).
        used: (K,) bool, intervals in the final solve (valid, inside the IMU stream, not
            outliers).
        sigma: rad, the residuals' standard deviation per axis.
    """

    bias_gyro: np.ndarray
    cov: np.ndarray
    residuals: np.ndarray
    per_interval: np.ndarray
    used: np.ndarray
    sigma: float



def gyro_bias_least_squares(imu: ImuData, rotations: VisualRotations, *,
                            bias0: np.ndarray | None = None, iterations: int = 3,
                            outlier_mad: float = 5.0) -> tuple[np.ndarray, GyroBiasFit]:
    """The gyro bias (3,) rad/s that best aligns the preintegrated gyro with ``rotations``.

    Each valid interval inside the IMU stream is preintegrated at full rate at the current
    bias; one Gauss-Newton step (:func:`gyro_bias_from_relative_rotations`) updates the bias,
    ``iterations`` times. At every iteration the intervals whose post-fit residual norm is
    more than ``outlier_mad`` scaled MADs above the median are dropped and the step refitted.

    Args:
        imu: the IMU stream (as recorded: the estimate is the total constant error, sensor
            bias plus any offset, that ``gyro - bias`` removes).
        rotations: :class:`VisualRotations` (body frame).
        bias0: (3,) the starting bias (zeros).

    Returns:
        ``(bias_gyro (3,), GyroBiasFit)``.

    Raises:
        DataError: fewer than 2 usable intervals.
    """
    t = np.asarray(imu.t_ns, np.int64)
    K = len(rotations.t0_ns)
    ok = (np.asarray(rotations.valid, bool) & (rotations.t0_ns >= t[0])
          & (rotations.t1_ns <= t[-1]) & (rotations.t1_ns > rotations.t0_ns))
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        raise DataError(f"{len(idx)} usable visual rotations inside the IMU stream (need 2)")
    batch = interval_batch(t, imu.gyro, imu.accel, rotations.t0_ns[idx], rotations.t1_ns[idx])
    R_vis = np.asarray(rotations.R, np.float64)[idx]
    bg = np.zeros(3) if bias0 is None else np.asarray(bias0, np.float64).reshape(3)
    keep = np.ones(len(idx), bool)

    def linearise(bg):
        pim = preintegrate(batch.dt, batch.gyro, batch.accel, bg, mask=batch.mask)
        return np.asarray(pim.delta_R, np.float64), np.asarray(pim.d_R_d_bg, np.float64)

    for _ in range(int(iterations)):
        dR, J = linearise(bg)
        e = rotation_residuals(R_vis, dR)
        for _ in range(2):  # solve, drop outliers by the post-fit residual, solve again
            d = gyro_bias_from_relative_rotations(R_vis, dR, J, keep)
            keep = _mad_inliers(np.linalg.norm(e - J @ d, axis=1), outlier_mad)
        bg = bg + gyro_bias_from_relative_rotations(R_vis, dR, J, keep)
    dR, J = linearise(bg)
    e = rotation_residuals(R_vis, dR)
    A = J[keep].reshape(-1, 3)
    dof = max(3 * int(keep.sum()) - 3, 1)
    sigma = float(np.sqrt(np.sum(e[keep] ** 2) / dof))
    cov = sigma**2 * np.linalg.inv(A.T @ A)
    residuals = np.full((K, 3), np.nan)
    residuals[idx] = e
    per = np.full((K, 3), np.nan)
    per[idx[keep]] = bg + np.linalg.solve(J[keep], e[keep][..., None])[..., 0]
    used = np.zeros(K, bool)
    used[idx[keep]] = True
    return bg, GyroBiasFit(bias_gyro=bg, cov=cov, residuals=residuals, per_interval=per,
                           used=used, sigma=sigma)


def _mad_inliers(r: np.ndarray, k: float) -> np.ndarray:
    med = float(np.median(r))
    mad = 1.4826 * float(np.median(np.abs(r - med)))
    return r <= med + k * max(mad, 1e-12)


def visual_gyro_bias(sequence: Sequence, config: VisualGyroConfig | None = None, *,
                     cache: bool = True, progress: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``visual-ls`` estimator: the gyro's constant error (3,) rad/s from the recording's
    own frames and IMU, no ground truth (accelerometer: not observable this way).

    Args:
        sequence: a recording with a camera, its extrinsic and an IMU stream.
        config: :class:`VisualGyroConfig`.
        cache: keep the visual rotations beside the recording (:func:`~uavcal_jax.vio.
            rotation_cache.cached_relative_rotations`) when it has a folder.

    Returns:
        ``(bias_gyro (3,) rad/s, per_interval (K, 3) rad/s: the bias each used interval alone
        implies, NaN for unused ones, times (K,) s: the intervals' mid-points)``.
    """
    config = config if config is not None else VisualGyroConfig()
    if sequence.imu is None:
        raise DataError("no IMU stream", sequence.root or sequence.name)
    rotations = cached_relative_rotations if cache else relative_rotations
    rot = rotations(sequence, config.frontend, every=config.every, min_tracks=config.min_tracks,
                    min_parallax_px=config.min_parallax_px, progress=progress)
    bg, fit = gyro_bias_least_squares(sequence.imu, rot, iterations=config.iterations,
                                      outlier_mad=config.outlier_mad)
    times = 0.5 * (rot.t0_ns + rot.t1_ns).astype(np.float64) * 1e-9
    return bg, fit.per_interval, times
