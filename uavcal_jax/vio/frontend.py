"""Optical-flow stereo front end: Shi-Tomasi corners tracked by pyramidal Lucas-Kanade.

RPEOD sec. 3.1, with VINS-Fusion's ``FeatureTracker::trackImage`` as the guide to the details.
For each stereo frame :meth:`FeatureTracker.track`:

1. equalises both images (histogram or CLAHE, see ``FrontendConfig.equalize``);
2. tracks the previous left corners into the new left image with ``calcOpticalFlowPyrLK``
   (seeded by the gyro-predicted positions when a rotation is given), tracks them back and
   keeps those landing within ``fb_threshold_px`` of where they started, away from the border;
3. rejects outliers by RANSAC on the undistorted points (VINS-Mono's ``rejectWithF``; VINS-
   Fusion has it commented out), its consensus checked against the IMU-predicted motion when
   the back end's velocity is given (:mod:`uavcal_jax.vio.match_checks`: a moving object that
   fills the view must not outvote the static scene);
4. keeps the surviving corners at least ``min_distance_px`` apart, longest-tracked first, and
   when fewer than ``redetect_below`` remain adds ``goodFeaturesToTrack`` corners outside their
   exclusion circles, up to ``max_features``, each with a new persistent id;
5. tracks every left corner into the right image with the same forward-backward check
   (seeded by its previous disparity when it had a match in the previous frame) and keeps the
   matches consistent with the known extrinsic (epipolar distance, a triangulation in front
   of the camera or at infinity).

The output, :class:`FrameFeatures`, has fixed capacity ``max_features`` with masks, so the
back end's arrays keep their shapes. Coordinates: pixels ``(u, v)`` with integer values at
pixel centres (OpenCV's convention); undistorted normalised ``(x/z, y/z)`` in each camera's
frame (x right, y down, z forward), computed with OpenCV's radial-tangential model -- the
model of :mod:`uavcal_jax.geometry.camera` -- iterated to convergence.

One job, one class: the tracker keeps the corners, their ids and ages between frames; its
stages share that state, so they stay together (the checks on matches already live in
:mod:`~uavcal_jax.vio.match_checks`, the statistics of a frame in
:mod:`~uavcal_jax.vio.frontend_stats`).

One module over 450 lines, one job: the front end's per-frame tracking (corners, flow both
ways, stereo matching, outlier rejection) as one stateful tracker; its statistics live in
:mod:`uavcal_jax.vio.frontend_stats`.
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

from uavcal_jax.data.sequence import CameraCalibration, Sequence
from uavcal_jax.geometry.camera import from_calibration
from uavcal_jax.vio.config import FrontendConfig
from uavcal_jax.vio.keyframes import body_to_camera_rotation
from uavcal_jax.vio.match_checks import (
    imu_consistent_inliers,
    reject_outliers,
    stereo_epipolar_distance,
    stereo_in_front,
)

__all__ = ["FeatureTracker", "FrameFeatures"]

# cv2.undistortPoints' default criteria (5 iterations) leave ~0.5 px error in EuRoC's corners.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)
#: Stages timed in ``FeatureTracker.last_timings`` (milliseconds), besides ``"total"``.
_STAGES = ("preprocess", "temporal", "outlier", "detect", "stereo")


@dataclasses.dataclass(frozen=True)
class FrameFeatures:
    """The features of one stereo frame, padded to the tracker's ``max_features`` rows.

    Rows ``mask == False`` are padding (id -1, coordinates 0). Valid rows come first, ordered
    longest-tracked first, then the corners detected in this frame.

    Attributes:
        t: frame time, seconds.
        ids: (N,) int64 persistent feature ids (-1 for padding).
        mask: (N,) bool, valid rows.
        uv: (N, 2) float64 left-image pixels.
        xy: (N, 2) float64 left undistorted normalised coordinates.
        uv_right: (N, 2) float64 right-image pixels of the stereo matches.
        xy_right: (N, 2) float64 right undistorted normalised coordinates (right camera frame).
        stereo_mask: (N,) bool, rows with a right observation (a subset of ``mask``).
        age: (N,) int32 frames the feature has been seen in, this one included (1 = new).
    """

    t: float
    ids: np.ndarray
    mask: np.ndarray
    uv: np.ndarray
    xy: np.ndarray
    uv_right: np.ndarray
    xy_right: np.ndarray
    stereo_mask: np.ndarray
    age: np.ndarray

    @property
    def n_tracked(self) -> int:
        """Valid features (tracked and new)."""
        return int(self.mask.sum())

    @property
    def n_stereo(self) -> int:
        """Valid features with a right observation."""
        return int(self.stereo_mask.sum())

    @property
    def n_new(self) -> int:
        """Features detected in this frame."""
        return int((self.mask & (self.age == 1)).sum())


class FeatureTracker:
    """Stateful stereo KLT tracker (the OpenCV edge of the VIO; the numerics after it are pure).

    Args:
        left: the left camera's calibration (intrinsics, distortion, ``T_BS``).
        right: the right camera's calibration, or ``None`` for a monocular front end.
        config: tracker settings (default :class:`FrontendConfig`'s).
    """

    def __init__(self, left: CameraCalibration, right: CameraCalibration | None = None,
                 config: FrontendConfig | None = None):
        self.config = config = config if config is not None else FrontendConfig()
        for cal in (left, right):
            if cal is not None:
                from_calibration(cal)  # raises on a lens model other than radial-tangential
        self.left = left
        self.right = right
        self.K0 = np.asarray(left.K, dtype=np.float64)
        self.D0 = np.asarray(left.distortion, dtype=np.float64)
        self.T_BC0 = np.asarray(left.T_BS, dtype=np.float64)
        self.T_C0B = np.linalg.inv(self.T_BC0)
        self.R_BC0 = self.T_BC0[:3, :3]
        if right is not None:
            self.K1 = np.asarray(right.K, dtype=np.float64)
            self.D1 = np.asarray(right.distortion, dtype=np.float64)
            self.T_C0C1 = np.linalg.inv(np.asarray(left.T_BS, np.float64)) @ np.asarray(
                right.T_BS, np.float64)
        self._clahe = (cv2.createCLAHE(config.clahe_clip, (config.clahe_tiles,) * 2)
                       if config.equalize == "clahe" else None)
        win = (config.lk_window_px, config.lk_window_px)
        self._lk = dict(winSize=win, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                               config.lk_iterations, config.lk_epsilon))
        #: Milliseconds spent in each stage of the last :meth:`track` call.
        self.last_timings: dict[str, float] = {}
        self._next_id = 0
        self.reset()

    @classmethod
    def from_sequence(cls, sequence: Sequence, config: FrontendConfig | None = None,
                      left: str = "cam0", right: str | None = "cam1") -> FeatureTracker:
        """A tracker for a sequence's cameras (monocular when ``right`` is absent)."""
        right_cal = (sequence.cameras[right].calibration
                     if right is not None and right in sequence.cameras else None)
        return cls(sequence.camera(left).calibration, right_cal, config)

    def reset(self) -> None:
        """Forget every track (ids keep increasing, so a reset never reuses one)."""
        self._img = None
        self._pts = np.zeros((0, 2), np.float32)
        # the last frame's stereo matches: ids (sorted) and right-minus-left pixel offsets
        self._disp_ids = np.zeros(0, np.int64)
        self._disp = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._age = np.zeros(0, np.int32)
        # per corner, the last frame's flow that the gyro rotation did not explain, pixels
        self._trans_flow = np.zeros((0, 2), np.float32)

    def equalised(self, img: np.ndarray) -> np.ndarray:
        """One (H, W) or (H, W, 3) image as the tracker sees it: grey uint8, equalised."""
        return self._prepare(img)[0]

    def normalised(self, uv: np.ndarray, right: bool = False) -> np.ndarray:
        """(N, 2) pixels of the left camera (or the right) -> (N, 2) undistorted normalised
        image coordinates."""
        return self._undistort(uv, self.K1, self.D1) if right else self._undistort(
            uv, self.K0, self.D0)

    @property
    def lk_params(self) -> dict:
        """The tracker's Lucas-Kanade window and stopping criteria (OpenCV keywords)."""
        return dict(self._lk)

    # --- stages ---------------------------------------------------------------------------

    def _prepare(self, img: np.ndarray | None) -> tuple[np.ndarray | None, bool]:
        """(equalised uint8 gray image, whether it has texture) -- ``(None, False)`` for None."""
        if img is None:
            return None, False
        img = np.asarray(img)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        if img.dtype != np.uint8:
            img = np.clip(np.nan_to_num(img), 0, 255).astype(np.uint8)
        img = np.ascontiguousarray(img)
        textured = img.size > 0 and float(cv2.meanStdDev(img)[1][0, 0]) >= self.config.min_contrast
        if self.config.equalize == "histogram":
            img = cv2.equalizeHist(img)
        elif self._clahe is not None:
            img = self._clahe.apply(img)
        return img, textured

    def _undistort(self, uv: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
        if len(uv) == 0:
            return np.zeros((0, 2))
        xy = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2), K, D, None, None,
                                 criteria=_UNDISTORT_CRITERIA)
        return xy.reshape(-1, 2)

    def _in_border(self, uv: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        b = self.config.border_px
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        return (u >= b) & (u < shape[1] - b) & (v >= b) & (v < shape[0] - b)

    def _flow_fb(self, img0, img1, pts0, guess=None, back_guess=None):
        """Forward LK ``img0 -> img1`` and the backward check; returns (pts1, ok).

        A seeded pass (``guess``) searches ``predicted_max_level`` levels around the seed;
        with ``retry_unseeded`` the corners it loses are searched again from scratch on
        ``lk_max_level`` levels: a seed that misses (the translation's flow, which a gyro
        seed leaves out, beyond the short search; 20-45 px a frame at 7 m/s under a ceiling
        1.8 m away, 376 px wide) otherwise ends half the tracks of a fast flight."""
        pts1, ok = self._flow_fb_once(img0, img1, pts0, guess, back_guess)
        if guess is not None and self.config.retry_unseeded and not ok.all():
            lost = ~ok
            pts1[lost], ok[lost] = self._flow_fb_once(img0, img1, pts0[lost])
        return pts1, ok

    def _flow_fb_once(self, img0, img1, pts0, guess=None, back_guess=None):
        """One forward LK pass and its backward check (seeded, or from scratch when the seed
        keeps fewer than ``min_predicted_tracked`` corners, as VINS); returns (pts1, ok)."""
        cfg = self.config
        if guess is not None:
            pts1, st, _ = cv2.calcOpticalFlowPyrLK(
                img0, img1, pts0, guess.copy(), maxLevel=cfg.predicted_max_level,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk)
            if int(st.sum()) < cfg.min_predicted_tracked:
                guess = back_guess = None
        if guess is None:
            pts1, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, pts0, None,
                                                   maxLevel=cfg.lk_max_level, **self._lk)
        # Tracking back from where the forward pass landed (not from the answer): seeding it
        # with pts0 would let a wrong forward match converge back and pass the check.
        if back_guess is None:
            back, st_b, _ = cv2.calcOpticalFlowPyrLK(img1, img0, pts1, None,
                                                     maxLevel=cfg.lk_max_level, **self._lk)
        else:
            back, st_b, _ = cv2.calcOpticalFlowPyrLK(
                img1, img0, pts1, (pts1 + back_guess).astype(np.float32),
                maxLevel=cfg.predicted_max_level, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk)
        pts1, back = pts1.reshape(-1, 2), back.reshape(-1, 2)
        ok = (st.reshape(-1) == 1) & (st_b.reshape(-1) == 1)
        ok &= np.linalg.norm(back - pts0.reshape(-1, 2), axis=1) <= cfg.fb_threshold_px
        ok &= self._in_border(pts1, img1.shape) & np.all(np.isfinite(pts1), axis=1)
        return pts1, ok

    def _stereo_flow(self, img, img_r, pts: np.ndarray, ids: np.ndarray):
        """Left-to-right LK with the forward-backward check; returns ``(uv_right, ok)``.

        A corner matched in the previous frame is seeded with that frame's disparity (the
        right-minus-left offset changes little from frame to frame) and tracked, like a
        gyro-seeded temporal track, on ``predicted_max_level`` pyramid levels; the others
        search the whole pyramid. Seeding halves the stereo stage's cost (one pyramid level
        instead of three for most corners); the forward-backward check is the same.
        """
        seeded = np.zeros(len(pts), bool)
        disp = np.zeros_like(pts)
        if self.config.stereo_seed_disparity and len(self._disp_ids):
            at = np.minimum(np.searchsorted(self._disp_ids, ids), len(self._disp_ids) - 1)
            seeded = self._disp_ids[at] == ids
            disp[seeded] = self._disp[at[seeded]]
        uv_r = np.zeros_like(pts)
        ok = np.zeros(len(pts), bool)
        if seeded.any():
            uv_r[seeded], ok[seeded] = self._flow_fb(img, img_r, pts[seeded],
                                                     pts[seeded] + disp[seeded], -disp[seeded])
        if not seeded.all():
            uv_r[~seeded], ok[~seeded] = self._flow_fb(img, img_r, pts[~seeded])
        return uv_r, ok

    def _camera_motion(self, R_b0_b1: np.ndarray, t_b0_b1: np.ndarray) -> np.ndarray:
        """(4, 4) the left camera's pose now in its previous frame, from the body's (rotation
        ``R_b0_b1``, translation ``t_b0_b1`` (3,) in the previous body frame)."""
        T_b0b1 = np.eye(4)
        T_b0b1[:3, :3], T_b0b1[:3, 3] = R_b0_b1, t_b0_b1
        return self.T_C0B @ T_b0b1 @ self.T_BC0

    def _predict(self, R_b0_b1: np.ndarray) -> np.ndarray:
        """Pixels of the previous corners after the body rotation ``R_b0_b1`` alone."""
        R_c0_c1 = body_to_camera_rotation(R_b0_b1, self.R_BC0)
        xy = self._undistort(self._pts, self.K0, self.D0)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R_c0_c1  # R^T r per row
        ahead = rays[:, 2] > 1e-6
        rays[~ahead] = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)[~ahead]
        uv, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K0,
                                  self.D0)
        uv = uv.reshape(-1, 2)
        uv[~ahead] = self._pts[~ahead]
        return uv.astype(np.float32)

    def _min_distance_mask(self, shape, pts: np.ndarray, age: np.ndarray):
        """VINS ``setMask``: keep tracks longest first, each outside the kept ones' circles."""
        mask = np.full(shape, 255, np.uint8)
        order = np.argsort(-age, kind="stable")
        keep = []
        r = int(round(self.config.min_distance_px))
        for i in order:
            u, v = int(round(pts[i, 0])), int(round(pts[i, 1]))
            if mask[v, u] == 255:
                keep.append(i)
                cv2.circle(mask, (u, v), r, 0, -1)
        return np.asarray(keep, dtype=np.int64), mask

    # --- the frame ------------------------------------------------------------------------

    def _excluded(self, uv: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """(N,) bool: the pixels ``uv (N, 2)`` inside any of ``boxes (M, 4)`` (``x0, y0, x1,
        y1``, pixel edges) grown by ``exclude_margin`` of their size on each side."""
        grown = _grow_boxes(boxes, self.config.exclude_margin)
        inside = ((uv[:, None, 0] >= grown[None, :, 0]) & (uv[:, None, 0] < grown[None, :, 2])
                  & (uv[:, None, 1] >= grown[None, :, 1]) & (uv[:, None, 1] < grown[None, :, 3]))
        return inside.any(axis=1)

    def track(self, t: float, img_left: np.ndarray, img_right: np.ndarray | None = None,
              R_prev_curr_gyro: np.ndarray | None = None, exclude: np.ndarray | None = None,
              t_prev_curr_body: np.ndarray | None = None) -> FrameFeatures:
        """Track one stereo frame.

        Args:
            t: frame time, seconds.
            img_left: (H, W) uint8 left image ((H, W, 3) RGB is converted to gray).
            img_right: (H, W) uint8 right image, or ``None`` (no stereo observations).
            R_prev_curr_gyro: (3, 3) body-frame (IMU-frame) rotation from the previous frame
                to this one, integrated from the gyro: maps body vectors now to the body frame
                at the previous frame. It seeds the optical flow; ``None``: no prediction.
            exclude: (M, 4) left-image boxes (``x0, y0, x1, y1``, pixels) of moving objects,
                or ``None``: tracks inside them (grown by ``exclude_margin``) end and no corner
                is detected there, so a target that fills the view does not outvote the
                static scene in the outlier check and the window.
            t_prev_curr_body: (3,) m, the body's predicted translation since the previous
                frame, in the previous body frame (the back end's velocity times the
                interval), or ``None``. With ``R_prev_curr_gyro`` it checks the outlier
                test's consensus (:func:`imu_consistent_inliers`).

        Returns:
            The frame's :class:`FrameFeatures`. Black, blank or textureless images give zero
            features; tracking resumes with new corners on the next textured frame.
        """
        cfg = self.config
        clock = time.perf_counter
        t0 = clock()
        img, textured = self._prepare(img_left)
        if not textured:
            # Nothing to track in or from: the next textured frame starts afresh.
            self.reset()
            self.last_timings = dict.fromkeys(_STAGES, 0.0) | {"total": 1e3 * (clock() - t0)}
            return self._pack(t, np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int32),
                              np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)),
                              np.zeros(0, bool))
        img_r = (self._prepare(img_right)[0] if (cfg.stereo and self.right is not None)
                 else None)
        if img_r is not None and img_r.shape != img.shape:
            img_r = None
        if self._img is not None and self._img.shape != img.shape:
            self.reset()
        t1 = clock()

        boxes = None if exclude is None else np.asarray(exclude, np.float64).reshape(-1, 4)
        pts, ids, age = self._pts, self._ids, self._age
        if len(pts) and self._img is not None:
            guess = back = None
            rot = pts
            if R_prev_curr_gyro is not None:
                rot = self._predict(R_prev_curr_gyro)
                guess = rot + self._trans_flow if cfg.seed_translation_flow else rot
                back = (pts - guess).astype(np.float32)
            cur, ok = self._flow_fb(self._img, img, pts, guess, back)
            # the flow the rotation does not explain (the translation's): the next frame's
            # seed adds it, the camera's velocity changing little in one frame
            trans_flow = (cur - rot).astype(np.float32)
            t2 = clock()
            if boxes is not None and len(boxes):
                # before the outlier check: a moving object's corners must not vote in it
                ok &= ~self._excluded(cur, boxes)
            if ok.any():
                xy0 = self._undistort(pts[ok], self.K0, self.D0)
                xy1 = self._undistort(cur[ok], self.K0, self.D0)
                inliers = reject_outliers(xy0, xy1, cfg)
                if R_prev_curr_gyro is not None and t_prev_curr_body is not None:
                    inliers = imu_consistent_inliers(
                        xy0, xy1, inliers, self._camera_motion(R_prev_curr_gyro,
                                                               t_prev_curr_body), cfg)
                ok[ok] = inliers
            pts, ids, age = cur[ok].astype(np.float32), ids[ok], age[ok] + 1
            trans_flow = trans_flow[ok]
        else:
            pts, ids, age = pts[:0], ids[:0], age[:0]
            trans_flow = np.zeros((0, 2), np.float32)
            t2 = clock()
        t3 = clock()

        self._img = img
        keep, mask = self._min_distance_mask(img.shape, pts, age)
        if boxes is not None:
            for x0, y0, x1, y1 in np.rint(_grow_boxes(boxes, cfg.exclude_margin)).astype(int):
                mask[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = 0
        pts, ids, age = pts[keep].reshape(-1, 2), ids[keep], age[keep]
        trans_flow = trans_flow[keep].reshape(-1, 2)
        n_new = cfg.max_features - len(pts)
        if len(pts) < cfg.redetect_below and n_new > 0:
            corners = cv2.goodFeaturesToTrack(img, n_new, cfg.quality_level, cfg.min_distance_px,
                                              mask=mask, blockSize=cfg.block_size)
            if corners is not None and len(corners):
                corners = corners.reshape(-1, 2).astype(np.float32)
                new_ids = np.arange(self._next_id, self._next_id + len(corners), dtype=np.int64)
                self._next_id += len(corners)
                pts = np.concatenate([pts, corners])
                ids = np.concatenate([ids, new_ids])
                age = np.concatenate([age, np.ones(len(corners), np.int32)])
                trans_flow = np.concatenate([trans_flow, np.zeros((len(corners), 2),
                                                                  np.float32)])
        self._pts, self._ids, self._age = pts, ids, age
        self._trans_flow = trans_flow
        xy = self._undistort(pts, self.K0, self.D0)
        t4 = clock()

        n = len(pts)
        uv_r = np.zeros((n, 2))
        xy_r = np.zeros((n, 2))
        st = np.zeros(n, bool)
        if img_r is not None and n:
            uv_r, st = self._stereo_flow(img, img_r, pts, ids)
            xy_r = self._undistort(uv_r, self.K1, self.D1)
            fx = float(self.K0[0, 0])
            st &= stereo_epipolar_distance(xy, xy_r, self.T_C0C1) * fx <= cfg.stereo_epipolar_px
            st &= stereo_in_front(xy, xy_r, self.T_C0C1, cfg.stereo_epipolar_px / fx)
            order = np.argsort(ids[st])
            self._disp_ids = ids[st][order]
            self._disp = (uv_r - pts)[st][order].astype(np.float32)
            uv_r = np.where(st[:, None], uv_r, 0.0)
            xy_r = np.where(st[:, None], xy_r, 0.0)
        t5 = clock()

        marks = [t0, t1, t2, t3, t4, t5]
        self.last_timings = {stage: 1e3 * (b - a) for stage, a, b in
                             zip(_STAGES, marks[:-1], marks[1:], strict=True)}
        self.last_timings["total"] = 1e3 * (t5 - t0)
        return self._pack(t, pts, ids, age, xy, uv_r, xy_r, st)

    def _pack(self, t, pts, ids, age, xy, uv_r, xy_r, st) -> FrameFeatures:
        n, cap = len(pts), self.config.max_features

        def pad(a, dtype, fill=0):
            out = np.full((cap, *np.shape(a)[1:]), fill, dtype=dtype)
            out[:n] = a
            return out

        return FrameFeatures(
            t=float(t),
            ids=pad(ids, np.int64, -1),
            mask=pad(np.ones(n, bool), bool, False),
            uv=pad(pts, np.float64),
            xy=pad(xy, np.float64),
            uv_right=pad(uv_r, np.float64),
            xy_right=pad(xy_r, np.float64),
            stereo_mask=pad(st, bool, False),
            age=pad(age, np.int32),
        )


def _grow_boxes(boxes: np.ndarray, margin: float) -> np.ndarray:
    """``boxes (M, 4)`` (``x0, y0, x1, y1``) grown by ``margin`` of their width and height on
    each side."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    pad = margin * np.concatenate([boxes[:, 2:] - boxes[:, :2]] * 2, axis=1)
    return boxes + pad * np.array([-1.0, -1.0, 1.0, 1.0])
