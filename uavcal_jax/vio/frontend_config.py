"""Configuration of the visual front end and of the keyframe decision (frozen dataclasses).

The defaults are VINS-Fusion's EuRoC settings (``config/euroc/euroc_stereo_imu_config.yaml``
and ``feature_tracker.cpp``) where RPEOD (sec. 3.1) leaves them open; the re-detection
threshold of 120 tracked corners is RPEOD's.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["EQUALIZERS", "ESTIMATORS", "OUTLIER_METHODS", "FrontendConfig", "KeyframeConfig"]

#: Frame-to-frame outlier rejection on undistorted points (see :class:`FrontendConfig`).
OUTLIER_METHODS = ("fundamental", "essential", "none")
#: Robust estimators of that rejection (see :class:`FrontendConfig`).
ESTIMATORS = ("usac", "ransac")
#: Image equalisation before tracking (see :class:`FrontendConfig`).
EQUALIZERS = ("histogram", "clahe", "none")


@dataclasses.dataclass(frozen=True)
class FrontendConfig:
    """The optical-flow feature tracker (:class:`uavcal_jax.vio.frontend.FeatureTracker`).

    Attributes:
        max_features: capacity of a frame's feature arrays and the most corners kept
            (VINS ``max_cnt``: 150).
        min_distance_px: corners are kept at least this far apart, pixels (VINS ``min_dist``).
        redetect_below: new corners are detected when fewer than this many are tracked
            (RPEOD sec. 3.1: 120).
        quality_level, block_size: ``cv2.goodFeaturesToTrack``'s Shi-Tomasi quality (relative
            to the best corner; VINS 0.01) and its derivative covariation block (pixels).
        lk_window_px: side of the square Lucas-Kanade window, pixels (VINS 21).
        lk_max_level: ``calcOpticalFlowPyrLK``'s ``maxLevel`` (VINS 3: the image plus three
            halvings).
        lk_iterations, lk_epsilon: the LK stopping criteria (OpenCV's and VINS's 30, 0.01).
        predicted_max_level: ``maxLevel`` when a gyro prediction seeds the flow (VINS 1); when
            fewer than ``min_predicted_tracked`` corners survive, the flow is rerun from scratch
            with ``lk_max_level`` as VINS does.
        min_predicted_tracked: see ``predicted_max_level`` (VINS 10).
        fb_threshold_px: a track is kept when tracking it back lands within this distance of
            where it started, pixels (VINS 0.5).
        border_px: tracks closer than this to the image edge are dropped (VINS 1).
        outlier_method: ``"fundamental"`` (RANSAC on the fundamental matrix of undistorted
            points on a virtual pinhole, as VINS-Mono's ``rejectWithF``), ``"essential"``
            (RANSAC on the essential matrix of normalised points) or ``"none"``.
        estimator: ``"usac"`` (OpenCV's USAC: RANSAC with local optimisation; the 8-point
            solver for the fundamental matrix, the 5-point one for the essential matrix) or
            ``"ransac"`` (OpenCV's classic RANSAC, VINS's ``FM_RANSAC``). On 150 synthetic
            matches with 0.2 px noise and a 1 px threshold the classic one drops 6-14 % of
            the correct matches (its answer is the best minimal sample, never refined);
            USAC keeps all of them, rejects the same outliers, and is no slower.
        ransac_threshold_px: RANSAC's epipolar distance on the virtual pinhole, pixels
            (VINS ``F_threshold``: 1).
        ransac_confidence: RANSAC's confidence (VINS 0.99).
        virtual_focal_px: focal length of the virtual pinhole the undistorted points are put
            on for RANSAC (VINS ``FOCAL_LENGTH``: 460).
        stereo: track the left corners into the right image when one is given.
        stereo_epipolar_px: a left-right match is kept when its symmetric distance to the
            epipolar lines of the known extrinsic is at most this, in normalised units times
            the left focal length (pixels); ``math.inf`` switches the check off (VINS-Fusion
            has none; its back end sees every forward-backward-consistent match).
        stereo_seed_disparity: a corner matched left-to-right in the previous frame starts
            its stereo LK at that frame's disparity on ``predicted_max_level`` levels (as a
            gyro-seeded temporal track; fewer than ``min_predicted_tracked`` survivors rerun
            it from scratch); ``False``: every corner searches all ``lk_max_level`` levels.
        equalize: how both images are equalised before tracking. ``"clahe"`` is VINS-Mono's
            ``equalize: 1`` on EuRoC (``clahe_clip`` and ``clahe_tiles``: its clip limit and
            tile grid, VINS 3.0 and 8x8); ``"histogram"`` is ``cv2.equalizeHist``; ``"none"``
            tracks raw intensities. Lucas-Kanade assumes constant brightness and EuRoC's two
            cameras differ in gain (mean 145 vs 130 in V1_01), so without equalisation only
            ~35 of 150 corners find their stereo match there; both equalisers give ~75. The
            default is ``"histogram"``: on the V1_01 micro slice it matched slightly more
            corners (77 vs 73 per frame, the same epipolar residuals) and the tracker ran
            ~30 % faster per frame, CLAHE's amplified fine texture making LK iterate longer.
        min_contrast: a left image whose intensity standard deviation (gray levels, before
            equalisation) is below this is textureless -- black, blank, lens covered: every
            track ends there and no corner is detected, since equalisation would turn its
            sensor noise into corners that track nothing.
    """

    max_features: int = 150
    min_distance_px: float = 30.0
    redetect_below: int = 120
    quality_level: float = 0.01
    block_size: int = 3
    lk_window_px: int = 21
    lk_max_level: int = 3
    lk_iterations: int = 30
    lk_epsilon: float = 0.01
    predicted_max_level: int = 1
    min_predicted_tracked: int = 10
    fb_threshold_px: float = 0.5
    border_px: int = 1
    outlier_method: str = "fundamental"
    estimator: str = "usac"
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.99
    virtual_focal_px: float = 460.0
    stereo: bool = True
    stereo_epipolar_px: float = 1.5
    stereo_seed_disparity: bool = True
    equalize: str = "histogram"
    clahe_clip: float = 3.0
    clahe_tiles: int = 8
    min_contrast: float = 2.0

    def __post_init__(self):
        if self.outlier_method not in OUTLIER_METHODS:
            raise ValueError(f"outlier_method must be one of {OUTLIER_METHODS}, "
                             f"got {self.outlier_method!r}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if self.equalize not in EQUALIZERS:
            raise ValueError(f"equalize must be one of {EQUALIZERS}, got {self.equalize!r}")
        if self.max_features < 1 or not 0 <= self.redetect_below <= self.max_features:
            raise ValueError("need max_features >= 1 and 0 <= redetect_below <= max_features")
        if self.lk_window_px < 3 or self.lk_window_px % 2 == 0:
            raise ValueError("lk_window_px must be an odd number >= 3")
        positive = (self.min_distance_px, self.fb_threshold_px, self.ransac_threshold_px,
                    self.virtual_focal_px, self.stereo_epipolar_px, self.quality_level)
        if not all(v > 0 for v in positive) or math.isnan(sum(positive)):
            raise ValueError("distances, thresholds, focal and quality level must be positive")


@dataclasses.dataclass(frozen=True)
class KeyframeConfig:
    """The keyframe decision (:func:`uavcal_jax.vio.keyframes.keyframe_decision`).

    Attributes:
        min_parallax_px: a frame is a keyframe when the mean rotation-compensated parallax of
            the features it shares with the last keyframe reaches this, in pixels at
            ``focal_px`` (VINS ``keyframe_parallax``: 10).
        focal_px: the focal length that converts normalised parallax to pixels (VINS
            ``FOCAL_LENGTH``: 460), so the threshold does not depend on the lens.
        min_tracked: a frame with fewer valid features than this is a keyframe (VINS: 20).
        min_common: a frame sharing fewer features than this with the last keyframe is a
            keyframe (VINS' ``long_track_num < 40``).
    """

    min_parallax_px: float = 10.0
    focal_px: float = 460.0
    min_tracked: int = 20
    min_common: int = 40

    def __post_init__(self):
        if not (self.min_parallax_px > 0 and self.focal_px > 0):
            raise ValueError("min_parallax_px and focal_px must be positive")
        if self.min_tracked < 0 or self.min_common < 0:
            raise ValueError("min_tracked and min_common must be >= 0")
