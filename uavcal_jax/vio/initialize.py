"""Stereo-inertial initialisation: gravity-aligned attitude from the accelerometer, stereo
triangulation, the gauge prior on the first keyframe, and the gyroscope bias from visual
rotations (VINS-Mono's ``solveGyroscopeBias``, on keyframe or any relative rotations).

Frames: the world frame is gravity-aligned (z up, gravity ``-9.81 z``) with the yaw of the
first keyframe's body at zero and its origin at the first keyframe (or, after a reset, the
propagated state). NumPy, float64; the prior is returned as the back end's pytree.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.vio.config import InitialPrior
from uavcal_jax.vio.window import FRAME_DIM, Keyframes, Prior

__all__ = [
    "gauge_prior",
    "gravity_aligned_rotation",
    "level_keeping_heading",
    "gyro_bias_from_relative_rotations",
    "gyro_bias_from_rotations",
    "rotation_residuals",
    "triangulate_stereo",
    "yaw_of",
]


def _up(accel_mean: np.ndarray) -> np.ndarray:
    """(3,) the unit "up" of an accelerometer reading (3,) m/s^2; ``ValueError`` where it is
    not finite or nearly zero (free fall or a dead sensor)."""
    a = np.asarray(accel_mean, np.float64).reshape(3)
    n = float(np.linalg.norm(a))
    if not np.isfinite(n) or n < 1.0:
        raise ValueError(f"cannot level from an accelerometer reading of norm {n:.3g} m/s^2")
    return a / n


def gravity_aligned_rotation(accel_mean: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """Body-to-world rotation (3, 3) whose body z-axis measurement ``accel_mean`` (3,) m/s^2
    (the specific force of a body at rest or in uniform motion points up, world ``+z``) maps to
    world ``+z``, with the given yaw (rad) about world z.

    Raises:
        ValueError: ``accel_mean`` is not finite or nearly zero (free fall or a dead sensor).
    """
    # the smallest rotation taking the measured "up" (body) to world z
    R, _ = Rotation.align_vectors(np.array([[0.0, 0.0, 1.0]]), _up(accel_mean)[None])
    R = R.as_matrix()
    return Rotation.from_euler("z", yaw - yaw_of(R)).as_matrix() @ R


def level_keeping_heading(accel_mean: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """Body-to-world rotation (3, 3) whose body measurement of "up" ``accel_mean`` (3,) maps to
    world ``+z``, nearest ``R_ref`` (3, 3): ``R_ref`` turned by the smallest world rotation,
    about a horizontal axis, that takes ``R_ref @ up`` to ``+z``. So the heading about world
    z is ``R_ref``'s whatever the body convention: a re-initialisation keeps the world frame.

    Why not :func:`yaw_of` and :func:`gravity_aligned_rotation`: the heading of the body's x
    axis is ill-defined where that axis is near vertical, as EuRoC's IMU frame has it (x
    up). There, re-levelling at ``yaw_of(R_ref)`` turned the world by 15-21 degrees per
    re-initialisation on a simulated V2_02 flight, and a target 8 m away moved by 3-4 m.

    Raises:
        ValueError: ``accel_mean`` is not finite or nearly zero.
    """
    R_ref = np.asarray(R_ref, np.float64)
    up_world = R_ref @ _up(accel_mean)
    correction, _ = Rotation.align_vectors(np.array([[0.0, 0.0, 1.0]]), up_world[None])
    return correction.as_matrix() @ R_ref


def yaw_of(R_WB: np.ndarray) -> float:
    """Yaw (rad) of a body-to-world rotation: the heading of its body x-axis in world xy
    (``atan2`` of the rotated x axis), the convention :func:`gravity_aligned_rotation` sets."""
    x = np.asarray(R_WB)[:, 0]
    return float(np.arctan2(x[1], x[0]))


def triangulate_stereo(xy_left: np.ndarray, xy_right: np.ndarray, T_C0C1: np.ndarray
                       ) -> np.ndarray:
    """Depths (N,) m along the left camera's z of stereo matches, by least squares.

    ``X0 = z0 (x0, y0, 1)`` and ``X0 = R z1 (x1, y1, 1) + t`` (``T_C0C1`` maps right-camera
    points into the left camera) give ``z0 b0 - z1 R b1 = t``, solved for ``(z0, z1)`` per
    match. Parallel rays (a point at infinity) give ``inf``; a point behind either camera a
    negative or non-finite value, which callers reject.

    Args:
        xy_left, xy_right: (N, 2) undistorted normalised coordinates.
        T_C0C1: (4, 4) pose of the right camera in the left camera's frame.
    """
    xy_left = np.asarray(xy_left, np.float64).reshape(-1, 2)
    xy_right = np.asarray(xy_right, np.float64).reshape(-1, 2)
    R, t = T_C0C1[:3, :3], T_C0C1[:3, 3]
    b0 = np.concatenate([xy_left, np.ones((len(xy_left), 1))], 1)
    b1 = np.concatenate([xy_right, np.ones((len(xy_right), 1))], 1) @ R.T
    # normal equations of [b0, -b1] (z0, z1) = t, 2x2 per match
    a11 = np.sum(b0 * b0, 1)
    a12 = -np.sum(b0 * b1, 1)
    a22 = np.sum(b1 * b1, 1)
    r0 = b0 @ t
    r1 = -(b1 @ t)
    det = a11 * a22 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        z0 = (a22 * r0 - a12 * r1) / det
        z1 = (a11 * r1 - a12 * r0) / det
    z0 = np.where(np.abs(det) < 1e-12 * a11 * a22, np.inf, z0)
    return np.where(z1 > 0, z0, -np.abs(z0))


def gauge_prior(frames: Keyframes, n_slots: int, sigma: InitialPrior,
                velocity_sigma: float | None = None) -> Prior:
    """The prior on keyframe slot 0 at (re-)initialisation (a :class:`Prior` over all slots,
    zero outside slot 0), centred on ``frames``' slot 0.

    Rotation information in the body tangent (right perturbation): ``1 / yaw`` along the world
    z-axis seen in the body (``R^T e_z``), ``1 / roll_pitch`` across it. Position, velocity and
    biases isotropic. ``velocity_sigma`` overrides ``sigma.velocity``.
    """
    R = np.asarray(frames.rotation[0], np.float64)
    up = R.T @ np.array([0.0, 0.0, 1.0])
    info_rot = (np.outer(up, up) / sigma.yaw**2
                + (np.eye(3) - np.outer(up, up)) / sigma.roll_pitch**2)
    sig_v = sigma.velocity if velocity_sigma is None else velocity_sigma
    diag = np.concatenate([np.full(3, 1 / sigma.position**2), np.full(3, 1 / sig_v**2),
                           np.full(3, 1 / sigma.bias_gyro**2), np.full(3, 1 / sigma.bias_accel**2)])
    info = np.zeros((FRAME_DIM, FRAME_DIM))
    info[:3, :3] = info_rot
    info[3:, 3:] = np.diag(diag)
    w, V = np.linalg.eigh(info)
    block = np.sqrt(w)[:, None] * V.T  # block^T block = info
    D = FRAME_DIM * n_slots
    J = np.zeros((D, D))
    J[:FRAME_DIM, :FRAME_DIM] = block
    return Prior(J=jnp.asarray(J), r=jnp.zeros(D), lin=frames, mask=jnp.asarray(True))


def rotation_residuals(R_rel: np.ndarray, delta_R: np.ndarray) -> np.ndarray:
    """(K, 3) rad, ``log(delta_R_k^T R_rel_k)``: how far each visual relative rotation is
    from the preintegrated one, in the body tangent at the interval's end (right perturbation).

    Args:
        R_rel: (K, 3, 3) visual relative rotations ``R_k^T R_{k+1}`` (map body vectors at the
            interval's end to the body frame at its start).
        delta_R: (K, 3, 3) preintegrated rotations of the same intervals (same convention).
    """
    err = np.einsum("kji,kjl->kil", np.asarray(delta_R, np.float64),
                    np.asarray(R_rel, np.float64))
    return Rotation.from_matrix(err).as_rotvec().reshape(-1, 3)


def gyro_bias_from_relative_rotations(R_rel: np.ndarray, delta_R: np.ndarray,
                                      d_R_d_bg: np.ndarray, weights: np.ndarray | None = None
                                      ) -> np.ndarray:
    """The gyro-bias correction (3,) rad/s that best aligns preintegrated rotations with
    visual relative rotations, one (weighted) Gauss-Newton step (VINS-Mono
    ``solveGyroscopeBias`` on relative rotations: the intervals need not be consecutive).

    ``delta_R(bg + d) ~= delta_R exp(d_R_d_bg d)``, so each interval gives
    ``log(delta_R^T R_rel) ~= d_R_d_bg d`` (:func:`rotation_residuals`); stacked, solved by
    least squares, row ``k`` weighted by ``weights[k]`` (default 1; 0 drops the interval).

    Args:
        R_rel: (K, 3, 3) visual relative rotations (body frame at the end to the start).
        delta_R: (K, 3, 3) preintegrated rotations of the same intervals.
        d_R_d_bg: (K, 3, 3) their right-perturbation bias Jacobians.
        weights: (K,) non-negative weights, or ``None``.
    """
    e = rotation_residuals(R_rel, delta_R)
    A = np.asarray(d_R_d_bg, np.float64).reshape(-1, 3, 3)
    if weights is not None:
        w = np.sqrt(np.asarray(weights, np.float64).reshape(-1))
        e, A = e * w[:, None], A * w[:, None, None]
    d, *_ = np.linalg.lstsq(A.reshape(-1, 3), e.reshape(-1), rcond=None)
    return d


def gyro_bias_from_rotations(R_WB: np.ndarray, delta_R: np.ndarray, d_R_d_bg: np.ndarray
                             ) -> np.ndarray:
    """The gyro-bias correction (3,) rad/s that best aligns preintegrated rotations with the
    keyframes' rotations (VINS-Mono ``solveGyroscopeBias``), one Gauss-Newton step.

    :func:`gyro_bias_from_relative_rotations` on the consecutive keyframes' relative
    rotations ``R_k^T R_{k+1}``.

    Args:
        R_WB: (K + 1, 3, 3) keyframe body-to-world rotations (visual estimates).
        delta_R: (K, 3, 3) preintegrated rotations of the intervals between them.
        d_R_d_bg: (K, 3, 3) their right-perturbation bias Jacobians.
    """
    R_WB = np.asarray(R_WB, np.float64)
    rel = np.einsum("kji,kjl->kil", R_WB[:-1], R_WB[1:])  # R_k^T R_{k+1}
    return gyro_bias_from_relative_rotations(rel, delta_R, d_R_d_bg)
