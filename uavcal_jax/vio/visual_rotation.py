"""The camera's relative rotations between frames from the front end's tracks: two-view
geometry, one pair at a time and over a recording.

:func:`relative_rotations` runs the project's KLT front end
(:class:`~uavcal_jax.vio.frontend.FeatureTracker`, monocular on the left camera: the
stereo stage adds nothing to the left tracks) over the recording and, for each pair of
frames ``(k, k + every)``, fits the camera's rotation to the tracks both frames share: an
essential matrix by RANSAC on undistorted normalised points (``cv2.findEssentialMat``,
focal 1, the front end's threshold ``ransac_threshold_px / NOMINAL_FOCAL_PX``), of whose
two rotations (``cv2.decomposeEssentialMat``) the one nearer a rotation-only fit is kept,
refined with the translation direction on the inliers' Sampson distances. When the
rotation-compensated parallax is below ``min_parallax_px`` (no translation to speak of:
hover, a pure turn) the rotation-only fit (Kabsch on the bearing vectors) is the answer.
The camera rotation is carried into the body (IMU) frame through the camera's extrinsic
``T_BS``: ``R_B = R_BC R_C R_BC^T``. The tracker is never given the gyro (its flow
prediction is off), so the visual rotations do not depend on the gyro or its bias.

Why not ``cv2.recoverPose`` and the rotation-only fit as a fallback at small parallax
(measured on a 40 s simulated V2_01 flight, 20 Hz pairs, median parallax 0.8 px): the
cheirality vote of ``recoverPose`` picks the wrong one of the twisted pair (180 deg off)
for a third of the pairs, whose translation is a few millimetres; RANSAC's rotation (its
best minimal sample) has a median error of 0.07 deg, the refined one 0.010 deg; and the
rotation-only fit absorbs the translation's parallax into the rotation (median error
0.15 deg, a gyro bias wrong by up to 0.03 rad/s), worse than the refined essential matrix
at every parallax measured, down to 0.3 px.

The cache of these rotations beside a recording is :mod:`uavcal_jax.vio.rotation_cache`; the
gyro bias they imply, :mod:`uavcal_jax.vio.visual_gyro`.

Conventions: ``R[k]`` maps body-frame vectors at ``t1_ns[k]`` to the body frame at
``t0_ns[k]`` (``R_WB(t0)^T R_WB(t1)``), the convention of a preintegrated ``delta_R`` and of
the front end's ``R_prev_curr_gyro``. NumPy, float64; times int64 nanoseconds.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import cv2
import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.vio.config import NOMINAL_FOCAL_PX, FrontendConfig
from uavcal_jax.vio.frontend import FeatureTracker

__all__ = [
    "METHODS",
    "MIN_PARALLAX_PX",
    "MIN_TRACKS",
    "VisualRotations",
    "relative_rotations",
    "timed_relative_rotations",
]

#: How a pair's rotation was found (``VisualRotations.method``): none (too few tracks, the
#: pair is invalid), the essential matrix, or the rotation-only fit (too little parallax).
METHODS = ("none", "essential", "rotation")
#: Fewest shared tracks (and inliers) for a pair to count (the default; the estimator's
#: ``VisualGyroConfig.min_tracks``).
MIN_TRACKS = 20
#: The median rotation-compensated parallax (pixels at the nominal focal) below which the
#: rotation-only fit is used (the default; ``VisualGyroConfig.min_parallax_px``).
MIN_PARALLAX_PX = 0.1


class VisualRotations(NamedTuple):
    """Relative body rotations between pairs of frames (K pairs).

    Attributes:
        t0_ns, t1_ns: (K,) int64 times of the pair's first and second frame.
        R: (K, 3, 3) body-frame (IMU-frame) rotation from ``t1`` to ``t0``: maps body vectors
            at ``t1`` to the body frame at ``t0`` (``R_WB(t0)^T R_WB(t1)``); identity where
            not ``valid``.
        inliers: (K,) int64 tracks the fit kept.
        valid: (K,) bool, a rotation was found (enough tracks and inliers).
        method: (K,) int8 index into :data:`METHODS`.
        parallax_px: (K,) median rotation-compensated parallax, pixels at the nominal focal.
    """

    t0_ns: np.ndarray
    t1_ns: np.ndarray
    R: np.ndarray
    inliers: np.ndarray
    valid: np.ndarray
    method: np.ndarray
    parallax_px: np.ndarray



# --- one pair -----------------------------------------------------------------------------


def _bearings(xy: np.ndarray) -> np.ndarray:
    b = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _kabsch(b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """(3, 3) ``R`` minimising ``sum |b0_i - R b1_i|^2`` (unit bearings (N, 3))."""
    U, _, Vt = np.linalg.svd(b1.T @ b0)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _angles(b0: np.ndarray, b1: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N,) rad between ``b0`` and ``R b1``."""
    return np.arccos(np.clip(np.sum(b0 * (b1 @ R.T), axis=1), -1.0, 1.0))


def _rotation_only(b0: np.ndarray, b1: np.ndarray, threshold: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch on bearings, refitted twice on the matches within ``threshold`` rad (or within
    3 median residuals when that is larger, so translation parallax does not drop them all).
    Returns ``(R_c0_c1, inlier mask)``."""
    keep = np.ones(len(b0), bool)
    R = _kabsch(b0, b1)
    for _ in range(2):
        a = _angles(b0, b1, R)
        keep = a <= max(threshold, 3.0 * float(np.median(a)))
        if keep.sum() < 3:
            break
        R = _kabsch(b0[keep], b1[keep])
    return R, keep


def _skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) cross-product matrix of a (3,) vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


_GENERATORS = np.stack([_skew(e) for e in np.eye(3)])


def _sampson(R: np.ndarray, t: np.ndarray, X0: np.ndarray, X1: np.ndarray, B: np.ndarray):
    """Sampson distances (N,) of the matches ``X0``, ``X1`` (N, 3 homogeneous normalised) to
    ``E = [t]x R`` (``R``, ``t`` map frame-0 points into frame 1), and their Jacobian (N, 5)
    with respect to ``R exp(a)`` and ``t + B b`` (``B`` (2, 3) spans the tangent at ``t``)."""
    E = _skew(t) @ R
    # dE/da_j = [t]x R [e_j]x,  dE/db_k = [B_k]x R
    dE = np.concatenate([E @ _GENERATORS, np.stack([_skew(b) @ R for b in B])])
    Ex0, Etx1 = X0 @ E.T, X1 @ E
    dEx0 = np.einsum("nj,mij->mni", X0, dE)
    dEtx1 = np.einsum("ni,mij->mnj", X1, dE)
    den = np.maximum(np.sqrt(np.sum(Ex0[:, :2] ** 2, 1) + np.sum(Etx1[:, :2] ** 2, 1)), 1e-300)
    r = np.sum(X1 * Ex0, axis=1) / den
    d_num = np.einsum("ni,mni->nm", X1, dEx0)
    d_den = (np.einsum("ni,mni->nm", Ex0[:, :2], dEx0[..., :2])
             + np.einsum("ni,mni->nm", Etx1[:, :2], dEtx1[..., :2])) / den[:, None]
    return r, (d_num - r[:, None] * d_den) / den[:, None]


def _tangent(t: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal rows orthogonal to the unit vector ``t``."""
    return np.linalg.svd(t[None])[2][1:]


def _levenberg_marquardt(R: np.ndarray, t: np.ndarray, X0: np.ndarray, X1: np.ndarray,
                         iterations: int, lam: float = 1e-4
                         ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(R, t, cost, lam)``: the Sampson cost (sum of squares) minimised from ``(R, t)`` by
    Levenberg-Marquardt over ``R exp(a)``, ``t + B b``; ``lam`` the damping to resume with."""
    B = _tangent(t)
    r, J = _sampson(R, t, X0, X1, B)
    cost = float(r @ r)
    for _ in range(iterations):
        H = J.T @ J
        step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-30), -J.T @ r)
        R_new = R @ cv2.Rodrigues(step[:3])[0]
        t_new = t + step[3:] @ B
        t_new /= np.linalg.norm(t_new)
        B_new = _tangent(t_new)
        r_new, J_new = _sampson(R_new, t_new, X0, X1, B_new)
        if float(r_new @ r_new) < cost:
            R, t, B, r, J = R_new, t_new, B_new, r_new, J_new
            done = cost - float(r @ r) < 1e-6 * cost
            cost, lam = float(r @ r), lam * 0.1
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return R, t, cost, lam


#: Translation directions the refinement also starts from (a hemisphere: the Sampson cost is
#: the same for ``t`` and ``-t``): for a 20 Hz pair the cost has local minima in ``t`` (the
#: rotation-translation ambiguity of a small motion), and RANSAC's ``t`` lies in a wrong one
#: for about one pair in ten (rotation errors of 0.1-0.4 deg).
_T_STARTS = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1], [1, -1, 1], [-1, 1, 1],
                      [-1, -1, 1]], np.float64)
_T_STARTS /= np.linalg.norm(_T_STARTS, axis=1, keepdims=True)


def _refine_essential(R: np.ndarray, t: np.ndarray, X0: np.ndarray, X1: np.ndarray,
                      iterations: int = 20, probe: int = 3) -> np.ndarray:
    """``R`` (frame 0 to frame 1) refined with a translation direction on the Sampson
    distances of the RANSAC inliers ``X0``, ``X1`` (N, 3), by Levenberg-Marquardt: ``probe``
    iterations from RANSAC's ``t`` and from each of :data:`_T_STARTS`, then the lowest-cost
    start to convergence.

    RANSAC's answer is its best minimal sample, several times noisier than a fit to all the
    inliers (median error 0.07 deg against 0.010 deg on the simulated V2_01 flight).
    """
    fits = [_levenberg_marquardt(R, t0, X0, X1, probe)
            for t0 in (t / np.linalg.norm(t), *_T_STARTS)]
    R, t, _, lam = min(fits, key=lambda f: f[2])
    return _levenberg_marquardt(R, t, X0, X1, iterations, lam)[0]


def _pair_rotation(xy0: np.ndarray, xy1: np.ndarray, threshold: float, min_tracks: int,
                   min_parallax: float, confidence: float):
    """Camera rotation ``R_c0_c1`` (maps camera vectors at frame 1 to frame 0) from matched
    normalised points (N, 2) of frames 0 and 1. Returns ``(R, inliers, method, parallax)``,
    ``method`` an index into :data:`METHODS`, ``parallax`` in normalised units (the median
    angle between the matches left by the rotation-only fit)."""
    n = len(xy0)
    if n < min_tracks:
        return np.eye(3), 0, 0, np.nan
    b0, b1 = _bearings(xy0), _bearings(xy1)
    R_rot, keep = _rotation_only(b0, b1, threshold)
    parallax = float(np.median(_angles(b0, b1, R_rot)[keep])) if keep.any() else np.nan
    if parallax >= min_parallax:
        try:
            E, inl = cv2.findEssentialMat(xy0, xy1, np.eye(3), cv2.RANSAC, confidence,
                                          threshold)
        except cv2.error:
            E = None
        if E is not None and E.shape[0] >= 3 and inl is not None:
            inl = inl.reshape(-1).astype(bool)
            if inl.sum() >= min_tracks:
                # Of E's two rotations (the "twisted pair", 180 deg apart) the one near the
                # rotation-only fit: recoverPose's cheirality vote picks the wrong one for a
                # third of 20 Hz frame pairs, whose translation is a few millimetres.
                R1, R2, t = cv2.decomposeEssentialMat(E[:3])
                R_c1c0 = max((R1, R2), key=lambda Q: np.trace(Q @ R_rot))  # Q ~ R_rot^T
                X0 = np.concatenate([xy0[inl], np.ones((inl.sum(), 1))], axis=1)
                X1 = np.concatenate([xy1[inl], np.ones((inl.sum(), 1))], axis=1)
                R_c1c0 = _refine_essential(R_c1c0, t.reshape(3), X0, X1)
                return R_c1c0.T, int(inl.sum()), 1, parallax
    n_in = int(keep.sum())
    if n_in < min_tracks:
        return np.eye(3), n_in, 0, parallax
    return R_rot, n_in, 2, parallax


# --- a recording --------------------------------------------------------------------------


def relative_rotations(sequence: Sequence, config: FrontendConfig | None = None, *,
                       every: int = 1, min_tracks: int = MIN_TRACKS,
                       min_parallax_px: float = MIN_PARALLAX_PX,
                       camera: str = "cam0", progress: bool = False) -> VisualRotations:
    """Body-frame relative rotations between frames ``(0, every), (every, 2 every), ...`` of
    ``sequence``'s ``camera``, from the front end's tracks (module docstring).

    Args:
        sequence: a recording with that camera (its calibration's ``T_BS`` is the camera-IMU
            extrinsic).
        config: the tracker's settings (default :class:`FrontendConfig`'s).
        every: frames per pair (>= 1).
        min_tracks, min_parallax_px: :data:`MIN_TRACKS`, :data:`MIN_PARALLAX_PX`.
        camera: the camera to track.
        progress: show a progress bar.

    Returns:
        :class:`VisualRotations` (:func:`timed_relative_rotations` also gives the time per
        frame).
    """
    return timed_relative_rotations(sequence, config, every=every, min_tracks=min_tracks,
                                    min_parallax_px=min_parallax_px, camera=camera,
                                    progress=progress)[0]


def timed_relative_rotations(sequence: Sequence, config: FrontendConfig | None = None, *,
                             every: int = 1, min_tracks: int = MIN_TRACKS,
                             min_parallax_px: float = MIN_PARALLAX_PX,
                             camera: str = "cam0", progress: bool = False
                             ) -> tuple[VisualRotations, float]:
    """:func:`relative_rotations` and the wall time it took per frame, seconds (image loading,
    tracking and the fits)."""
    config = config if config is not None else FrontendConfig()
    every = int(every)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    start = time.perf_counter()
    cam = sequence.camera(camera)
    # monocular: the left tracks do not depend on the stereo stage; no gyro prediction, so
    # nothing here depends on the gyro or its bias
    tracker = FeatureTracker(cam.calibration, None, config)
    R_BC = np.asarray(cam.calibration.T_BS, np.float64)[:3, :3]
    threshold = config.ransac_threshold_px / NOMINAL_FOCAL_PX
    min_parallax = min_parallax_px / NOMINAL_FOCAL_PX
    n = len(cam)
    firsts = np.arange(0, n - every, every)
    K = len(firsts)
    R = np.tile(np.eye(3), (K, 1, 1))
    inliers = np.zeros(K, np.int64)
    method = np.zeros(K, np.int8)
    parallax = np.full(K, np.nan)
    prev = None  # (ids, xy) of the pair's first frame
    for i in progress_bar(range(n if K else 0), total=n, desc="visual rotations",
                          enabled=progress, unit="frame"):
        if i > firsts[-1] + every:
            break
        f = tracker.track(float(cam.t_ns[i]) * 1e-9, cam.load(i))
        ids, xy = f.ids[f.mask], f.xy[f.mask]
        if i % every:
            continue
        if prev is not None:
            k = i // every - 1
            _, a, b = np.intersect1d(prev[0], ids, assume_unique=True, return_indices=True)
            R_c, inliers[k], method[k], parallax[k] = _pair_rotation(
                prev[1][a], xy[b], threshold, min_tracks, min_parallax,
                config.ransac_confidence)
            R[k] = R_BC @ R_c @ R_BC.T
        prev = (ids, xy)
    seconds = (time.perf_counter() - start) / max(n, 1)
    t = np.asarray(cam.t_ns, np.int64)
    return VisualRotations(t0_ns=t[firsts], t1_ns=t[firsts + every], R=R, inliers=inliers,
                           valid=method > 0, method=method,
                           parallax_px=parallax * NOMINAL_FOCAL_PX), seconds
