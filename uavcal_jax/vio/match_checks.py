"""Geometric checks of point matches, pure functions of undistorted normalised coordinates
(the front end's steps 3 and 5, :mod:`uavcal_jax.vio.frontend`): RANSAC outlier rejection of
frame-to-frame matches (:func:`reject_outliers`), its check against the IMU-predicted motion
(:func:`imu_consistent_inliers`), and the stereo matches' epipolar distance
(:func:`stereo_epipolar_distance`) and cheirality (:func:`stereo_in_front`).
"""

from __future__ import annotations

import cv2
import numpy as np

from uavcal_jax.vio.config import NOMINAL_FOCAL_PX, FrontendConfig

__all__ = ["imu_consistent_inliers", "reject_outliers", "stereo_epipolar_distance",
           "stereo_in_front"]

# RANSAC needs at least this many points (the 8-point / 5-point minimal sets plus margin).
_MIN_RANSAC_POINTS = 8


def stereo_epipolar_distance(xy_left: np.ndarray, xy_right: np.ndarray,
                             T_C0C1: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distance of stereo matches, normalised units.

    With ``X0 = R X1 + t`` (``T_C0C1`` maps right-camera points to the left camera) the
    essential matrix ``E = [t]x R`` gives ``x0^T E x1 = 0`` for homogeneous normalised points.

    Args:
        xy_left: (N, 2) undistorted normalised left coordinates.
        xy_right: (N, 2) undistorted normalised right coordinates.
        T_C0C1: (4, 4) pose of the right camera in the left camera's frame.

    Returns:
        (N,) the mean of the distance of ``x0`` to the line ``E x1`` and of ``x1`` to the line
        ``E^T x0``, each in its own normalised plane (multiply by a focal length for pixels).
    """
    R, t = T_C0C1[:3, :3], T_C0C1[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ R
    x0 = np.concatenate([xy_left, np.ones((len(xy_left), 1))], axis=1)
    x1 = np.concatenate([xy_right, np.ones((len(xy_right), 1))], axis=1)
    l0 = x1 @ E.T  # lines E x1 in the left image
    l1 = x0 @ E  # lines E^T x0 in the right image
    r = np.abs(np.sum(x0 * l0, axis=1))
    d0 = r / np.maximum(np.hypot(l0[:, 0], l0[:, 1]), 1e-300)
    d1 = r / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-300)
    return 0.5 * (d0 + d1)


def reject_outliers(xy0: np.ndarray, xy1: np.ndarray, config: FrontendConfig) -> np.ndarray:
    """RANSAC inliers of frame-to-frame matches of undistorted normalised points.

    With ``config.outlier_method`` ``"fundamental"`` a fundamental matrix is fitted (by
    ``config.estimator``) to the points put on a virtual pinhole of focal
    :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX` (VINS-Mono's ``rejectWithF``; centring
    it on the image, as VINS does, changes nothing: OpenCV normalises the points first); with
    ``"essential"`` an essential matrix to the normalised points, threshold
    ``ransac_threshold_px / NOMINAL_FOCAL_PX``. ``"none"`` keeps everything, as do fewer than
    8 matches and a degenerate set that gives no model (OpenCV returns none, raises, or finds
    fewer inliers than a minimal sample).

    Args:
        xy0, xy1: (N, 2) the matches in the previous and the current frame.
        config: the thresholds.

    Returns:
        (N,) bool, the inliers.
    """
    n = len(xy0)
    if config.outlier_method == "none" or n < _MIN_RANSAC_POINTS:
        return np.ones(n, bool)
    xy0, xy1 = np.asarray(xy0, np.float64), np.asarray(xy1, np.float64)
    usac = config.estimator == "usac"
    try:
        if config.outlier_method == "fundamental":
            f = NOMINAL_FOCAL_PX
            _, inl = cv2.findFundamentalMat(xy0 * f, xy1 * f,
                                            cv2.USAC_FM_8PTS if usac else cv2.FM_RANSAC,
                                            config.ransac_threshold_px, config.ransac_confidence)
        else:
            _, inl = cv2.findEssentialMat(xy0, xy1, np.eye(3),
                                          cv2.USAC_DEFAULT if usac else cv2.RANSAC,
                                          config.ransac_confidence,
                                          config.ransac_threshold_px / NOMINAL_FOCAL_PX)
    except cv2.error:
        # OpenCV 5's USAC asserts (``!model.empty()``) where 4.x returned no model, on match
        # sets with no non-degenerate 8-point sample (seen on a simulated EuRoC flight)
        inl = None
    inl = None if inl is None else inl.reshape(-1)[:n].astype(bool)
    # a model has at least its minimal sample as inliers: fewer means USAC found none (it
    # returns an all-zero mask on e.g. coincident points), not that every match is wrong
    return np.ones(n, bool) if inl is None or inl.sum() < _MIN_RANSAC_POINTS else inl


def imu_consistent_inliers(xy0: np.ndarray, xy1: np.ndarray, inliers: np.ndarray,
                           T_c0c1: np.ndarray, config: FrontendConfig) -> np.ndarray:
    """The RANSAC ``inliers`` (N,) bool of the matches ``xy0 -> xy1`` (N, 2) (undistorted
    normalised, previous and current frame), or, when the predicted camera motion ``T_c0c1``
    (4, 4: the current camera in the previous one's frame, from the gyro's rotation and the
    back end's velocity) does not explain them and does explain the rest, the consensus of the
    rest (:func:`reject_outliers` on them).

    A moving object that fills the view gives RANSAC its largest consensus, and the static
    scene becomes the outliers; the window then tracks the object. The rule compares medians
    of the point-to-epipolar-line distance under the prediction (pixels at
    :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX`, the translation's direction only): the
    consensus's above ``config.imu_consensus_px`` and the rest's below
    ``config.imu_consensus_ratio`` of it. A static scene's consensus agrees with the
    prediction and its outliers (mistracks) do not, so it is left as it is. Then the tracks of
    the consensus farther from their predicted lines than ``config.imu_gate_factor`` times its
    median (and ``config.imu_gate_px``) leave it: an object whose motion a fundamental matrix
    fits together with the scene's. With no translation predicted nothing is decided.
    """
    t = np.asarray(T_c0c1, np.float64)[:3, 3]
    rest = ~inliers
    if (not config.imu_consensus or np.linalg.norm(t) < 1e-9 or not inliers.any()
            or rest.sum() < _MIN_RANSAC_POINTS):
        return inliers
    unit = np.eye(4)
    unit[:3, :3], unit[:3, 3] = np.asarray(T_c0c1)[:3, :3], t / np.linalg.norm(t)
    error = stereo_epipolar_distance(xy0, xy1, unit) * NOMINAL_FOCAL_PX
    consensus, others = np.median(error[inliers]), np.median(error[rest])
    if consensus > config.imu_consensus_px and others < config.imu_consensus_ratio * consensus:
        swapped = np.zeros_like(inliers)
        swapped[rest] = reject_outliers(xy0[rest], xy1[rest], config)
        inliers = swapped if swapped.any() else inliers
    # a consensus that mixes the object with the scene: its tracks far off the prediction go
    if inliers.any():
        gate = max(config.imu_gate_px, config.imu_gate_factor * np.median(error[inliers]))
        inliers = inliers & (error <= gate)
    return inliers


def stereo_in_front(xy_left: np.ndarray, xy_right: np.ndarray, T_C0C1: np.ndarray,
                     tolerance: float) -> np.ndarray:
    """(N,) bool: the match triangulates in front of the left camera (``d0 b0 = d1 R b1 + t``
    in least squares), or its rays are parallel within ``tolerance`` radians (a point too far
    for its depth's sign to be known; it still constrains the rotation)."""
    R, t = T_C0C1[:3, :3], T_C0C1[:3, 3]
    b0 = np.concatenate([xy_left, np.ones((len(xy_left), 1))], axis=1)
    b1 = np.concatenate([xy_right, np.ones((len(xy_right), 1))], axis=1) @ R.T
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    # Normal equations of [b0, -b1] [d0, d1]^T = t, solved per row by Cramer's rule.
    b = -np.sum(b0 * b1, axis=1)
    det = 1.0 - b * b
    d0_det = (b0 @ t) + b * (b1 @ t)  # d0 * det
    parallel = det < tolerance**2  # 1 - cos^2 = sin^2 of the angle between the rays
    return parallel | (d0_det > 0)
