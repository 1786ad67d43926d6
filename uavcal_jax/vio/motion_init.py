"""Initialisation while moving: gravity and velocity from a short stretch of stereo frames and
the IMU, with no hover needed (the stereo rig fixes the scale, so this is VINS-Mono's linear
alignment without its scale unknown).

1. :func:`stereo_odometry`: each frame's camera pose relative to the first, by PnP of the
   previous frame's stereo-triangulated corners on their tracked positions (metric).
2. :func:`imu_deltas`: the accelerometer and gyro preintegrated over each frame interval in the
   interval's starting body frame (biases taken as zero: the window estimates them).
3. :func:`align_gravity_velocity`: with the visual body poses ``R_k, p_k`` (in the first body
   frame ``b0``) and the deltas ``alpha_k, beta_k``, every interval gives, linear in the
   velocities ``v_k`` and gravity ``g`` (all in ``b0``)::

       p_{k+1} - p_k - R_k alpha_k = v_k dt + g dt^2 / 2
       R_k beta_k                  = v_{k+1} - v_k - g dt

   solved by least squares, then again with ``|g|`` fixed to ``GRAVITY_NORM``.

Why: levelling the first keyframe by the accelerometer's mean assumes the body is not
accelerating. On a simulated UZH-FPV outdoor flight (outdoor_45_1, 2 s in, 1.2 m/s and
accelerating at ~3 m/s^2) that start is 18 deg off in tilt; the window never recovers it (its
accelerometer bias absorbs 1.7 m/s^2 of gravity) and the estimate leaves: ATE 9.4 m over a
41 m path, against 0.08 m over the first 24 m from the true start.

Pure NumPy (OpenCV for PnP), float64.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.vio.config import NOMINAL_FOCAL_PX
from uavcal_jax.vio.frontend import FrameFeatures
from uavcal_jax.vio.initialize import gravity_aligned_rotation, level_keeping_heading

__all__ = ["MotionInit", "align_gravity_velocity", "imu_deltas", "initialize_moving",
           "stereo_odometry"]

#: m/s^2, the norm gravity is fixed to in the second solve.
GRAVITY_NORM = float(np.linalg.norm(np.asarray(GRAVITY_W)))
#: Fewest PnP inliers for a frame-to-frame pose.
MIN_PNP_INLIERS = 12
#: PnP RANSAC threshold, normalised units (2 px at the nominal focal length).
PNP_THRESHOLD = 2.0 / NOMINAL_FOCAL_PX


@dataclasses.dataclass(frozen=True)
class MotionInit:
    """The outcome of :func:`initialize_moving` at the stretch's last frame.

    Attributes:
        rotation: (3, 3) body-to-world, gravity-aligned (heading as asked).
        velocity: (3,) m/s, world.
        gravity_norm: m/s^2, the unconstrained solve's ``|g|`` (a check on the odometry).
        residual_rms: the fixed-gravity solve's weighted residual RMS (sigmas).
    """

    rotation: np.ndarray
    velocity: np.ndarray
    gravity_norm: float
    residual_rms: float


def stereo_odometry(features: list[FrameFeatures], depths: list[tuple[np.ndarray, np.ndarray]]
                    ) -> np.ndarray | None:
    """(K, 4, 4) ``T_C0Ck``: each frame's left camera in the first frame's, or ``None`` when a
    frame shares fewer than :data:`MIN_PNP_INLIERS` PnP inliers with the one before.

    Args:
        features: K frames of the tracker's output, in order.
        depths: per frame ``(depth (N,) m, usable (N,) bool)`` of its stereo matches
            (:func:`~uavcal_jax.vio.slots.stereo_depths`).
    """
    T = [np.eye(4)]
    for prev, (d_prev, ok_prev), cur in zip(features[:-1], depths[:-1], features[1:],
                                            strict=True):
        sel = prev.mask & ok_prev
        ids_p = prev.ids[sel]
        X = np.concatenate([prev.xy[sel], np.ones((int(sel.sum()), 1))], 1) * d_prev[sel, None]
        _, i_p, i_c = np.intersect1d(ids_p, cur.ids[cur.mask], assume_unique=True,
                                     return_indices=True)
        if len(i_p) < MIN_PNP_INLIERS:
            return None
        obj = X[i_p].astype(np.float64)
        img = cur.xy[cur.mask][i_c].astype(np.float64)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, np.eye(3), None,
                                                 reprojectionError=PNP_THRESHOLD,
                                                 iterationsCount=100, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < MIN_PNP_INLIERS:
            return None
        inl = inl.reshape(-1)
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], np.eye(3), None, rvec, tvec)
        T_cur_prev = np.eye(4)
        T_cur_prev[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_cur_prev[:3, 3] = tvec.reshape(3)
        T.append(T[-1] @ np.linalg.inv(T_cur_prev))
    return np.stack(T)


def imu_deltas(dt: np.ndarray, gyro: np.ndarray, accel: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(alpha (3,), beta (3,), seconds)``: position and velocity increments of one interval's
    samples (``dt`` (S,) s, ``gyro`` (S, 3) rad/s, ``accel`` (S, 3) m/s^2) in the body frame at
    its start, gravity excluded, biases zero (midpoint rotation per sample)."""
    R = np.eye(3)
    a = np.zeros(3)
    v = np.zeros(3)
    for h, w, f in zip(dt, gyro, accel, strict=True):
        dR = Rotation.from_rotvec(w * h).as_matrix()
        Rm = R @ Rotation.from_rotvec(0.5 * w * h).as_matrix()
        acc = Rm @ f
        a += v * h + 0.5 * acc * h * h
        v += acc * h
        R = R @ dR
    return a, v, float(np.sum(dt))


def align_gravity_velocity(R: np.ndarray, p: np.ndarray, alpha: np.ndarray, beta: np.ndarray,
                           dt: np.ndarray, sigma_p: float = 0.01, sigma_v: float = 0.01
                           ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Velocities and gravity of K body poses (module docstring, step 3).

    Args:
        R, p: (K, 3, 3), (K, 3) body poses in the first body frame (visual, metric).
        alpha, beta: (K-1, 3) IMU position and velocity increments of each interval
            (:func:`imu_deltas`).  dt: (K-1,) interval lengths, s.
        sigma_p, sigma_v: the rows' standard deviations, m and m/s.

    Returns:
        ``(v (K, 3) m/s, g (3,) m/s^2, |g| of the free solve, residual RMS)``, in the first
        body frame, ``|g| = GRAVITY_NORM``.
    """
    K = len(p)
    n = 3 * K + 3
    rows, rhs = [], []
    I3 = np.eye(3)
    for k in range(K - 1):
        h = dt[k]
        A = np.zeros((3, n))
        A[:, 3 * k:3 * k + 3] = h * I3
        A[:, -3:] = 0.5 * h * h * I3
        rows.append(A / sigma_p)
        rhs.append((p[k + 1] - p[k] - R[k] @ alpha[k]) / sigma_p)
        B = np.zeros((3, n))
        B[:, 3 * k:3 * k + 3] = -I3
        B[:, 3 * k + 3:3 * k + 6] = I3
        B[:, -3:] = -h * I3
        rows.append(B / sigma_v)
        rhs.append(R[k] @ beta[k] / sigma_v)
    A, b = np.concatenate(rows), np.concatenate(rhs)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    g_free = x[-3:]
    g = GRAVITY_NORM * g_free / max(np.linalg.norm(g_free), 1e-9)
    # gravity fixed: the velocities alone
    x_v = np.linalg.lstsq(A[:, :-3], b - A[:, -3:] @ g, rcond=None)[0]
    r = A[:, :-3] @ x_v + A[:, -3:] @ g - b
    return x_v.reshape(K, 3), g, float(np.linalg.norm(g_free)), float(np.sqrt(np.mean(r * r)))


def initialize_moving(features: list[FrameFeatures], depths: list[tuple[np.ndarray, np.ndarray]],
                      imu_rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                      T_BC0: np.ndarray, reference: np.ndarray | None = None,
                      max_gravity_error: float = 1.0) -> MotionInit | None:
    """The body's gravity-aligned rotation and velocity at the last of ``features``' frames.

    Args:
        features: K >= 3 consecutive frames; ``depths`` their stereo depths
            (:func:`stereo_odometry`).
        imu_rows: K-1 intervals' raw ``(dt, gyro, accel)`` samples between the frames.
        T_BC0: (4, 4) left camera to body.
        reference: (3, 3) body-to-world rotation at the last frame whose heading the result
            keeps (:func:`~uavcal_jax.vio.initialize.level_keeping_heading`: the current
            estimate, so a re-initialisation does not turn the world); ``None``: yaw 0.
        max_gravity_error: m/s^2; a free solve whose ``|g|`` is further than this from
            ``GRAVITY_NORM`` means the odometry is off: ``None``.

    Returns:
        A :class:`MotionInit`, or ``None`` (odometry lost, or gravity implausible).
    """
    if len(features) < 3:
        return None
    T_c = stereo_odometry(features, depths)
    if T_c is None:
        return None
    T_BC0 = np.asarray(T_BC0, np.float64)
    T_b = T_BC0 @ T_c @ np.linalg.inv(T_BC0)  # T_B0Bk
    d = [imu_deltas(*row) for row in imu_rows]
    alpha = np.stack([x[0] for x in d])
    beta = np.stack([x[1] for x in d])
    dt = np.array([x[2] for x in d])
    v, g, g_norm, rms = align_gravity_velocity(T_b[:, :3, :3], T_b[:, :3, 3], alpha, beta, dt)
    if not (np.all(np.isfinite(v)) and abs(g_norm - GRAVITY_NORM) <= max_gravity_error):
        return None
    R_last = T_b[-1, :3, :3]
    # a body at rest would measure -g (its specific force points up): the levelling's input
    up = -(R_last.T @ g)
    R_WB = (gravity_aligned_rotation(up) if reference is None
            else level_keeping_heading(up, reference))
    v_world = R_WB @ R_last.T @ v[-1]
    return MotionInit(R_WB, v_world, g_norm, rms)
