"""Locate a box from a stereo pair (real recordings have no depth image).

OpenCV + NumPy for the images, then the depth-image path's numerics
(:mod:`uavcal_jax.track.locate`). Once per rig, :func:`rectify_stereo` runs
``cv2.stereoRectify`` on the two cameras' calibrations (intrinsics, radial-tangential
distortion, camera-to-body extrinsics) and builds the remap tables. Per box,
:func:`locate_box_stereo`:

1. rectifies both images and maps the left box into the rectified left image (its border,
   undistorted and rotated by ``R1``, bounded);
2. runs semi-global matching (``cv2.StereoSGBM``) on a horizontal strip of rows around the
   box (the whole width, for the disparity search), disparity -> z-depth ``f b / d``;
3. takes the robust depth of the box (:func:`~uavcal_jax.track.locate.box_depth`: low
   quantile, band, median) and unprojects the rectified box centre with the rectified
   (distortion-free) camera, the stereo noise model using the rig's own baseline and focal
   length; the rectified-left frame is rotated back to the left camera's by ``R1^T``.

Frames as in :mod:`uavcal_jax.track.locate`; ``T_BC`` are camera-to-body (4, 4). The left
camera is the reference; the right one must sit to its right (positive disparity), in a
horizontal rig.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax.numpy as jnp
import numpy as np

from uavcal_jax.geometry.camera import PinholeRadtan
from uavcal_jax.track.locate import (
    LocateConfig,
    Located,
    box_center,
    box_depth,
    locate_from_depth,
)

__all__ = [
    "StereoConfig",
    "StereoRectification",
    "box_disparity",
    "locate_box_stereo",
    "rectified_box",
    "rectify_images",
    "rectify_stereo",
]


@dataclasses.dataclass(frozen=True)
class StereoConfig:
    """Settings of the box's stereo matching (``cv2.StereoSGBM``).

    Attributes:
        num_disparities: disparity search range, pixels, a multiple of 16 (64: down to
            ``f b / 64`` metres, 0.8 m for EuRoC's rig).
        block_size: matching block, pixels (odd).
        margin: rows added above and below the box's strip (at least half a block).
        uniqueness: SGBM's ``uniquenessRatio``, percent.
    """

    num_disparities: int = 64
    block_size: int = 7
    margin: int = 8
    uniqueness: int = 10

    def __post_init__(self):
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ValueError(f"num_disparities must be a positive multiple of 16, "
                             f"got {self.num_disparities}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd and >= 1, got {self.block_size}")


@dataclasses.dataclass(frozen=True, eq=False)
class StereoRectification:
    """A rectified stereo rig (``cv2.stereoRectify``, zoomed so every pixel is valid).

    Attributes:
        camera: the rectified left camera (pinhole, no distortion), image size unchanged.
        R_left: (3, 3) ``R1``, left camera frame -> rectified left frame.
        baseline: metres.
        K_left, D_left: the left camera's matrix and ``k1, k2, p1, p2`` (OpenCV arrays).
        P_left: (3, 4) the rectified left projection ``P1``.
        maps_left, maps_right: ``cv2.remap`` tables of the two images.
    """

    camera: PinholeRadtan
    R_left: np.ndarray
    baseline: float
    K_left: np.ndarray
    D_left: np.ndarray
    P_left: np.ndarray
    maps_left: tuple[np.ndarray, np.ndarray]
    maps_right: tuple[np.ndarray, np.ndarray]


def _cv(cam: PinholeRadtan) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(cam.K, np.float64), np.asarray(cam.distortion, np.float64)


def rectify_stereo(cam_left: PinholeRadtan, cam_right: PinholeRadtan, T_BC_left, T_BC_right
                   ) -> StereoRectification:
    """Rectify a horizontal stereo rig from its calibration.

    Args:
        cam_left, cam_right: the two camera models (same image size).
        T_BC_left, T_BC_right: (4, 4) camera-to-body extrinsics.

    Raises:
        ValueError: the images differ in size, or the rig is not horizontal with the right
            camera to the right of the left one.
    """
    if cam_left.resolution != cam_right.resolution:
        raise ValueError(f"stereo cameras differ in size: {cam_left.resolution} vs "
                         f"{cam_right.resolution}")
    size = cam_left.resolution
    K1, D1 = _cv(cam_left)
    K2, D2 = _cv(cam_right)
    # OpenCV's R, T map left-camera points into the right camera: X2 = R X1 + T
    T_C2C1 = np.linalg.inv(np.asarray(T_BC_right, np.float64)) @ np.asarray(T_BC_left, np.float64)
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
        K1, D1, K2, D2, size, np.ascontiguousarray(T_C2C1[:3, :3]),
        np.ascontiguousarray(T_C2C1[:3, 3:4]), flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0.0)
    if abs(P2[1, 3]) > 1e-9 * max(1.0, abs(P2[0, 3])) or P2[0, 3] >= 0.0:
        raise ValueError("stereo rig is not horizontal with the right camera on the right "
                         f"(rectified P2 translation {P2[:, 3]})")
    baseline = float(-P2[0, 3] / P2[0, 0])
    camera = PinholeRadtan.create((P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]), (0.0,) * 4, size,
                                  dtype=jnp.result_type(cam_left.fx))
    maps_left = cv2.initUndistortRectifyMap(K1, D1, R1, P1, size, cv2.CV_32FC1)
    maps_right = cv2.initUndistortRectifyMap(K2, D2, R2, P2, size, cv2.CV_32FC1)
    return StereoRectification(camera, R1, baseline, K1, D1, P1, maps_left, maps_right)


def rectify_images(rect: StereoRectification, left: np.ndarray, right: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The pair (H, W) uint8 remapped into the rectified geometry (bilinear)."""
    return (cv2.remap(left, *rect.maps_left, cv2.INTER_LINEAR),
            cv2.remap(right, *rect.maps_right, cv2.INTER_LINEAR))


def rectified_box(rect: StereoRectification, box) -> np.ndarray:
    """(4,) the left-image box (pixel edges) mapped into the rectified left image: the bounds
    of its border (16 points a side), undistorted and rotated."""
    x1, y1, x2, y2 = (float(v) for v in box)
    s = np.linspace(0.0, 1.0, 16)
    # pixel-edge -> pixel-centre coordinates (the camera models' convention), and back
    xs, ys = x1 + s * (x2 - x1) - 0.5, y1 + s * (y2 - y1) - 0.5
    border = np.concatenate([
        np.stack([xs, np.full_like(s, y1 - 0.5)], 1), np.stack([xs, np.full_like(s, y2 - 0.5)], 1),
        np.stack([np.full_like(s, x1 - 0.5), ys], 1), np.stack([np.full_like(s, x2 - 0.5), ys], 1),
    ])
    out = cv2.undistortPoints(border[:, None, :], rect.K_left, rect.D_left, R=rect.R_left,
                              P=rect.P_left)[:, 0, :] + 0.5
    return np.concatenate([out.min(0), out.max(0)])


def box_disparity(left_rect: np.ndarray, right_rect: np.ndarray, box_rect,
                  config: StereoConfig = StereoConfig()) -> np.ndarray:
    """(H, W) float32 disparity, pixels, on the rows of ``box_rect`` (rectified pixel edges)
    plus ``margin``; NaN elsewhere and where SGBM finds no match.

    SGBM runs on that strip only (all columns: the right image's match lies left of the
    left pixel).
    """
    height = left_rect.shape[0]
    r0 = max(0, int(np.floor(box_rect[1])) - config.margin)
    r1 = min(height, int(np.ceil(box_rect[3])) + config.margin)
    out = np.full(left_rect.shape[:2], np.nan, np.float32)
    if r1 - r0 < config.block_size:
        return out
    b = config.block_size
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0, numDisparities=config.num_disparities, blockSize=b,
        P1=8 * b * b, P2=32 * b * b, uniquenessRatio=config.uniqueness,
        speckleWindowSize=0, disp12MaxDiff=1, mode=cv2.STEREO_SGBM_MODE_SGBM)
    disparity = sgbm.compute(np.ascontiguousarray(left_rect[r0:r1]),
                             np.ascontiguousarray(right_rect[r0:r1])).astype(np.float32) / 16.0
    out[r0:r1] = np.where(disparity > 0.0, disparity, np.nan)
    return out


def locate_box_stereo(box, left: np.ndarray, right: np.ndarray, rect: StereoRectification,
                      T_BC_left, T_WB, extent=None, config: LocateConfig | None = None,
                      stereo: StereoConfig = StereoConfig()) -> Located:
    """The world position of the target in ``box`` (left image, pixel edges) from a stereo
    pair.

    Args:
        box: ``(x1, y1, x2, y2)`` in the (unrectified) left image.
        left, right: (H, W) uint8 grey images.
        rect: the rig's :class:`StereoRectification`.
        T_BC_left: (4, 4) left camera-to-body; T_WB: (4, 4) the body pose.
        extent: the target's depth extent, metres (default ``config.target_extent``).
        config: :class:`~uavcal_jax.track.locate.LocateConfig` (default: its defaults; its
            ``baseline`` is replaced by the rig's).
        stereo: :class:`StereoConfig`.

    Returns:
        :class:`~uavcal_jax.track.locate.Located`.
    """
    left_r, right_r = rectify_images(rect, left, right)
    box_r = rectified_box(rect, box)
    disparity = box_disparity(left_r, right_r, box_r, stereo)
    depth = float(rect.P_left[0, 0]) * rect.baseline / disparity  # NaN stays NaN
    config = dataclasses.replace(config or LocateConfig(), baseline=rect.baseline)
    dtype = jnp.result_type(rect.camera.fx)
    measured = box_depth(jnp.asarray(depth, dtype), jnp.asarray(box_r, dtype), config)
    uv = box_center(jnp.asarray(box_r, dtype))
    T_CR = np.eye(4)  # rectified-left -> left camera: p_C = R1^T p_R
    T_CR[:3, :3] = np.asarray(rect.R_left).T
    T_WR = np.asarray(T_WB, np.float64) @ np.asarray(T_BC_left, np.float64) @ T_CR
    return locate_from_depth(uv, measured, rect.camera, jnp.asarray(T_WR, dtype), extent, config)
