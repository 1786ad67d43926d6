"""Keyframe decision: gyro-compensated parallax against the last keyframe (RPEOD sec. 3.1).

VINS-Fusion (``FeatureManager::compensatedParallax2``) measures the parallax of a feature
between two frames in normalised coordinates and has the rotation compensation commented
out, so a pure rotation -- which carries no depth information -- makes keyframes. Here the
last keyframe's bearings are first rotated into the current camera by the gyro-integrated
relative rotation, so only the translation-induced parallax counts.

Frames and conventions:

* ``R_kf_cur`` (3, 3) maps vectors in the *current* camera frame to the *keyframe's* camera
  frame (``X_kf = R_kf_cur @ X_cur`` for a pure rotation). :func:`body_to_camera_rotation`
  turns the gyro's body-frame (IMU-frame) rotation into it.
* Feature positions are undistorted normalised coordinates ``(x/z, y/z)`` of the camera frame
  (x right, y down, z forward); parallax is reported in pixels at
  :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX`.

Pure NumPy, float64.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uavcal_jax.vio.config import NOMINAL_FOCAL_PX, KeyframeConfig

__all__ = [
    "KeyframeDecision",
    "body_to_camera_rotation",
    "compensated_parallax",
    "keyframe_decision",
]


@dataclasses.dataclass(frozen=True)
class KeyframeDecision:
    """The outcome of :func:`keyframe_decision`.

    Attributes:
        is_keyframe: whether the current frame becomes a keyframe.
        reason: ``"first"``, ``"few_tracked"``, ``"few_common"``, ``"parallax"`` or ``""``
            (not a keyframe).
        parallax_px: mean rotation-compensated parallax over the shared features, pixels at
            :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX` (``nan`` when there are none).
        parallax_uncompensated_px: the same without the rotation compensation (VINS-Fusion's
            figure), for diagnostics.
        n_tracked: valid features in the current frame.
        n_common: features shared with the last keyframe (and in front of the current camera
            after the rotation).
    """

    is_keyframe: bool
    reason: str
    parallax_px: float
    parallax_uncompensated_px: float
    n_tracked: int
    n_common: int


def body_to_camera_rotation(R_b0_b1: np.ndarray, R_BC: np.ndarray) -> np.ndarray:
    """A relative rotation of the body (IMU) frame expressed in a rigidly mounted camera.

    Args:
        R_b0_b1: (3, 3) maps body-frame vectors at time 1 to the body frame at time 0 (the
            gyro integrated from 0 to 1).
        R_BC: (3, 3) camera-to-body rotation (the rotation part of the camera's ``T_BS``).

    Returns:
        (3, 3) ``R_c0_c1 = R_BC^T R_b0_b1 R_BC``, mapping camera vectors at time 1 to the camera
        frame at time 0.
    """
    R_b0_b1 = np.asarray(R_b0_b1, dtype=np.float64)
    R_BC = np.asarray(R_BC, dtype=np.float64)
    return R_BC.T @ R_b0_b1 @ R_BC


def compensated_parallax(xy_kf: np.ndarray, xy_cur: np.ndarray,
                         R_kf_cur: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature parallax between a keyframe and the current frame, rotation removed.

    Args:
        xy_kf: (N, 2) undistorted normalised coordinates in the keyframe.
        xy_cur: (N, 2) the same features' normalised coordinates in the current frame.
        R_kf_cur: (3, 3) current-to-keyframe camera rotation (module docstring); ``None`` is
            the identity (no compensation).

    Returns:
        ``(parallax, valid)``: (N,) Euclidean distances in the current normalised plane
        between each feature and its keyframe bearing rotated into the current camera
        (unitless; multiply by a focal length for pixels), and (N,) bool, False where the
        rotated bearing points behind the current camera (its parallax is then ``nan``).
    """
    xy_kf = np.asarray(xy_kf, dtype=np.float64).reshape(-1, 2)
    xy_cur = np.asarray(xy_cur, dtype=np.float64).reshape(-1, 2)
    rays = np.concatenate([xy_kf, np.ones_like(xy_kf[:, :1])], axis=1)
    if R_kf_cur is not None:
        # Row vectors: (R^T r)^T = r^T R.
        rays = rays @ np.asarray(R_kf_cur, dtype=np.float64)
    z = rays[:, 2]
    valid = z > 1e-9
    predicted = rays[:, :2] / np.where(valid, z, 1.0)[:, None]
    parallax = np.where(valid, np.linalg.norm(predicted - xy_cur, axis=1), np.nan)
    return parallax, valid


def keyframe_decision(kf_ids: np.ndarray | None, kf_xy: np.ndarray | None,
                      cur_ids: np.ndarray, cur_xy: np.ndarray, cur_mask: np.ndarray,
                      R_kf_cur: np.ndarray | None = None,
                      config: KeyframeConfig | None = None,
                      elapsed_s: float = float("inf")) -> KeyframeDecision:
    """Is the current frame a keyframe?

    It is when there is no keyframe yet, when it has fewer than ``config.min_tracked`` valid
    features, when it shares fewer than ``config.min_common`` with the last keyframe, or when
    the mean parallax of the shared features after removing the rotation ``R_kf_cur``
    (:func:`compensated_parallax`) is at least ``config.min_parallax_px`` pixels at
    :data:`~uavcal_jax.vio.config.NOMINAL_FOCAL_PX`, or when ``R_kf_cur`` turns by more than
    ``config.max_rotation_deg`` at least ``config.rotation_min_interval_s`` after the last
    keyframe (``elapsed_s``).

    Args:
        kf_ids: (M,) int feature ids of the last keyframe (padding ids < 0 are ignored), or
            ``None`` before the first keyframe.
        kf_xy: (M, 2) their undistorted normalised coordinates in the keyframe.
        cur_ids: (N,) int feature ids of the current frame.
        cur_xy: (N, 2) their undistorted normalised coordinates.
        cur_mask: (N,) bool, which of the current rows are valid features.
        R_kf_cur: (3, 3) current-to-keyframe camera rotation (from the gyro, see
            :func:`body_to_camera_rotation`); ``None`` measures the raw parallax.
        config: the thresholds (default :class:`KeyframeConfig`'s).
        elapsed_s: seconds since the last keyframe.

    Returns:
        A :class:`KeyframeDecision`.
    """
    config = config if config is not None else KeyframeConfig()
    cur_ids = np.asarray(cur_ids).reshape(-1)
    cur_mask = np.asarray(cur_mask, dtype=bool).reshape(-1) & (cur_ids >= 0)
    cur_xy = np.asarray(cur_xy, dtype=np.float64).reshape(-1, 2)
    n_tracked = int(cur_mask.sum())
    if kf_ids is None or kf_xy is None:
        return KeyframeDecision(True, "first", float("nan"), float("nan"), n_tracked, 0)

    kf_ids = np.asarray(kf_ids).reshape(-1)
    kf_xy = np.asarray(kf_xy, dtype=np.float64).reshape(-1, 2)
    kf_ok = kf_ids >= 0
    _, i_kf, i_cur = np.intersect1d(kf_ids[kf_ok], cur_ids[cur_mask], assume_unique=True,
                                    return_indices=True)
    xy_kf = kf_xy[kf_ok][i_kf]
    xy_cur = cur_xy[cur_mask][i_cur]
    parallax, valid = compensated_parallax(xy_kf, xy_cur, R_kf_cur)
    raw, _ = compensated_parallax(xy_kf, xy_cur, None)
    n_common = int(valid.sum())
    mean_px = float(np.mean(parallax[valid]) * NOMINAL_FOCAL_PX) if n_common else float("nan")
    raw_px = float(np.mean(raw) * NOMINAL_FOCAL_PX) if raw.size else float("nan")

    turned = 0.0 if R_kf_cur is None else float(np.degrees(np.arccos(np.clip(
        (np.trace(np.asarray(R_kf_cur, np.float64)) - 1.0) / 2.0, -1.0, 1.0))))
    if n_tracked < config.min_tracked:
        reason = "few_tracked"
    elif n_common < config.min_common:
        reason = "few_common"
    elif mean_px >= config.min_parallax_px:
        reason = "parallax"
    elif turned > config.max_rotation_deg and elapsed_s >= config.rotation_min_interval_s:
        reason = "rotation"
    else:
        reason = ""
    return KeyframeDecision(bool(reason), reason, mean_px, raw_px, n_tracked, n_common)
