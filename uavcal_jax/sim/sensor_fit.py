"""A camera's temporal noise measured from frames of a static scene: the noise curve
(variance against mean intensity, the photon-transfer curve) and its shot + read noise fit.

A pixel that sees a still scene varies from frame to frame only by the sensor's noise: shot
noise, whose variance in DN grows linearly with the signal (slope = the conversion gain, DN
per electron), and signal-independent read noise plus the 8-bit quantisation (1/12 DN^2):

    var(DN) = K * mean(DN) + read_dn^2 + 1/12

:func:`noise_curve` bins the pixels by their temporal mean and takes each bin's median
temporal variance; :func:`fit_shot_read` fits the line. Both are pure numpy functions; they
measure real frames (``euroc_v101_micro``) and simulated ones alike, so the two curves compare
directly (:mod:`uavcal_jax.sim.sensor` states the constants fitted this way).

Textured pixels of a real recording also vary with the rig's vibration (a sub-pixel shift
moves an edge's intensity), so only pixels with a small spatial gradient of the mean image
count (``max_gradient``), and pixels that ever clip (0 or 255) are left out (clipping removes
variance).

Vignetting (:func:`stereo_vignetting`) cannot be read off one camera's mean image: the scene's
own brightness varies across it as much. A stereo pair sees the same surface points at
different image positions, so the ratio of the two cameras' intensities of a point depends
only on the two cameras' gains and on the falloff at the two positions; a ``cos(theta)^p``
falloff (:mod:`uavcal_jax.sim.vignetting`) is fitted to those ratios over the matched pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from uavcal_jax.data.sequence import CameraCalibration

__all__ = ["ESTIMATORS", "NoiseCurve", "ShotReadFit", "VignettingFit", "fit_shot_read",
           "noise_curve", "stereo_vignetting", "temporal_variance"]

#: Temporal variance estimators: ``"difference"``, half the mean squared difference of
#: consecutive frames (blind to slow drifts of brightness: auto-exposure, lighting), or
#: ``"std"``, the variance of each pixel about its mean over all frames (ddof 1).
ESTIMATORS = ("difference", "std")
#: Variance of rounding a continuous value to integers, DN^2.
QUANTISATION_VARIANCE = 1.0 / 12.0


@dataclass(frozen=True)
class NoiseCurve:
    """Temporal noise against intensity, one entry per populated bin.

    Attributes:
        mean_dn: (B,) mean over the bin's pixels of their temporal mean, DN.
        variance_dn2: (B,) median over the bin's pixels of their temporal variance, DN^2.
        pixels: (B,) pixels in the bin.
    """

    mean_dn: np.ndarray
    variance_dn2: np.ndarray
    pixels: np.ndarray

    @property
    def std_dn(self) -> np.ndarray:
        """(B,) temporal standard deviation, DN."""
        return np.sqrt(self.variance_dn2)


@dataclass(frozen=True)
class ShotReadFit:
    """The line ``var = dn_per_electron * mean + intercept`` through a :class:`NoiseCurve`.

    Attributes:
        dn_per_electron: slope, the conversion gain (DN per electron).
        intercept_dn2: the dark variance, read noise plus quantisation, DN^2.
        slope_se, intercept_se: their standard errors (least squares).
    """

    dn_per_electron: float
    intercept_dn2: float
    slope_se: float
    intercept_se: float

    @property
    def read_noise_dn(self) -> float:
        """Read noise, DN rms: the intercept less quantisation (0 if the intercept is below it)."""
        return float(np.sqrt(max(self.intercept_dn2 - QUANTISATION_VARIANCE, 0.0)))

    @property
    def read_noise_electrons(self) -> float:
        """Read noise, electrons rms."""
        return self.read_noise_dn / self.dn_per_electron

    @property
    def full_scale_electrons(self) -> float:
        """Electrons that fill 0..255 at this conversion gain."""
        return 255.0 / self.dn_per_electron


def temporal_variance(frames: np.ndarray, estimator: str = "difference"
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel temporal mean and variance of ``frames`` (N, H, W) (N >= 2, any real dtype,
    DN) -> ``(mean (H, W), variance (H, W))`` in DN and DN^2 (:data:`ESTIMATORS`)."""
    x = np.asarray(frames, dtype=np.float64)
    if x.ndim != 3 or x.shape[0] < 2:
        raise ValueError(f"frames must be (N >= 2, H, W), got shape {x.shape}")
    if estimator == "difference":
        var = (np.diff(x, axis=0) ** 2).mean(axis=0) / 2.0
    elif estimator == "std":
        var = x.var(axis=0, ddof=1)
    else:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    return x.mean(axis=0), var


def noise_curve(frames: np.ndarray, *, estimator: str = "difference", bin_width: float = 10.0,
                lo: float = 10.0, hi: float = 250.0, max_gradient: float = 1.0,
                min_pixels: int = 500, dn_max: int = 255) -> NoiseCurve:
    """The noise curve of a static scene's frames.

    Args:
        frames: (N, H, W) gray frames of a still camera and scene, DN (N >= 2).
        estimator: temporal variance estimator (:data:`ESTIMATORS`).
        bin_width, lo, hi: mean-intensity bins ``[lo, lo + w), ...`` up to ``hi``, DN.
        max_gradient: keep pixels whose mean image's gradient magnitude (central differences,
            DN per pixel) is below this (``inf`` keeps all).
        min_pixels: drop bins with fewer pixels.
        dn_max: the saturation value; pixels that reach it or 0 in any frame are left out.

    Returns:
        The :class:`NoiseCurve` of the bins that have ``min_pixels``.
    """
    x = np.asarray(frames)
    mean, var = temporal_variance(x, estimator)
    keep = (x.max(axis=0) < dn_max) & (x.min(axis=0) > 0)
    if np.isfinite(max_gradient):
        keep &= np.hypot(*np.gradient(mean)) < max_gradient
    rows = []
    for b0 in np.arange(lo, hi, bin_width):
        sel = keep & (mean >= b0) & (mean < b0 + bin_width)
        if sel.sum() >= min_pixels:
            rows.append((mean[sel].mean(), np.median(var[sel]), int(sel.sum())))
    if not rows:
        return NoiseCurve(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    m, v, n = (np.asarray(c) for c in zip(*rows, strict=True))
    return NoiseCurve(mean_dn=m, variance_dn2=v, pixels=n.astype(np.int64))


def fit_shot_read(curve: NoiseCurve) -> ShotReadFit:
    """Least-squares line through the curve's (mean, variance) points (>= 3 bins)."""
    if curve.mean_dn.shape[0] < 3:
        raise ValueError(f"the noise curve needs >= 3 bins to fit, got {curve.mean_dn.shape[0]}")
    (slope, intercept), cov = np.polyfit(curve.mean_dn, curve.variance_dn2, 1, cov=True)
    return ShotReadFit(dn_per_electron=float(slope), intercept_dn2=float(intercept),
                       slope_se=float(np.sqrt(cov[0, 0])),
                       intercept_se=float(np.sqrt(cov[1, 1])))


@dataclass(frozen=True)
class VignettingFit:
    """A ``cos(theta)^p`` falloff fitted to a stereo pair's intensity ratios.

    Attributes:
        exponent: ``p``.
        exponent_se: its standard error, from a bootstrap over image blocks (pixels of one
            surface are not independent).
        log_gain_ratio: ``log(gain0 / gain1)``, the two cameras' brightness ratio on axis.
        pixels: matched pixels used.
    """

    exponent: float
    exponent_se: float
    log_gain_ratio: float
    pixels: int


def _cos_theta(P: np.ndarray, R_rect: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """cos of the angle to the original camera's optical axis of rectified pixels ``(u, v)``
    (``P`` the rectified projection, ``R_rect`` original -> rectified rotation)."""
    ray = np.stack([(u - P[0, 2]) / P[0, 0], (v - P[1, 2]) / P[1, 1], np.ones_like(u)], -1)
    original = ray @ R_rect  # R_rect^T applied to row vectors
    return original[..., 2] / np.linalg.norm(original, axis=-1)


def stereo_vignetting(frames0: np.ndarray, frames1: np.ndarray, calib0: CameraCalibration,
                      calib1: CameraCalibration, *, min_dn: float = 20.0,
                      max_gradient: float = 2.0, block: int = 60, bootstrap: int = 50,
                      seed: int = 0) -> VignettingFit:
    """Fit ``cos(theta)^p`` vignetting to a static stereo pair.

    The mean images are rectified (the calibrations' lenses and ``T_BS``), matched by
    semi-global block matching, and for each matched pixel with little texture (gradient below
    ``max_gradient`` DN/px, where a sub-pixel match error changes little), neither end
    saturated or below ``min_dn``, ``log I0 - log I1 = log(g0/g1) + p (log cos th0 - log cos
    th1)`` is fitted by least squares (a Lambertian scene).

    Args:
        frames0, frames1: (N, H, W) gray frames of the two cameras, DN (N >= 1).
        calib0, calib1: their calibrations (both of size W x H).
        block: side of the square image blocks the bootstrap resamples, pixels.
        bootstrap: resamples for the standard error.

    Returns:
        :class:`VignettingFit`.
    """
    x0, x1 = (np.asarray(f, np.float32) for f in (frames0, frames1))
    m0, m1 = x0.mean(axis=0), x1.mean(axis=0)
    T_10 = np.linalg.inv(calib1.T_BS) @ calib0.T_BS  # cam0 points into cam1
    size = tuple(int(v) for v in calib0.resolution)
    R0, R1, P0, P1, *_ = cv2.stereoRectify(
        calib0.K, np.asarray(calib0.distortion, float), calib1.K,
        np.asarray(calib1.distortion, float), size, T_10[:3, :3].copy(),
        T_10[:3, 3].reshape(3, 1).copy(), alpha=0)
    rect = []
    for m, x, c, R, P in ((m0, x0, calib0, R0, P0), (m1, x1, calib1, R1, P1)):
        mx, my = cv2.initUndistortRectifyMap(c.K, np.asarray(c.distortion, float), R, P, size,
                                             cv2.CV_32FC1)
        rect.append((cv2.remap(m, mx, my, cv2.INTER_LINEAR),
                     cv2.remap(x.max(axis=0), mx, my, cv2.INTER_NEAREST)))
    (r0, s0), (r1, s1) = rect
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=96, blockSize=7, P1=8 * 49,
                                 P2=32 * 49, uniquenessRatio=15, speckleWindowSize=100,
                                 speckleRange=2)
    disp = sgbm.compute(*(np.clip(r, 0, 255).astype(np.uint8) for r in (r0, r1))) / 16.0
    v, u = np.mgrid[0:size[1], 0:size[0]].astype(np.float32)
    u1 = (u - disp).astype(np.float32)
    i1 = cv2.remap(r1, u1, v, cv2.INTER_LINEAR)
    s1 = cv2.remap(s1, u1, v, cv2.INTER_NEAREST)
    grad = np.hypot(*np.gradient(cv2.GaussianBlur(r0, (0, 0), 1.0)))
    sel = (disp > 1) & (u1 > 5) & (r0 > min_dn) & (i1 > min_dn) & (s0 < 255) & (s1 < 255) \
        & (grad < max_gradient)
    y = np.log(r0[sel]) - np.log(i1[sel])
    a = np.log(_cos_theta(P0, R0, u, v)[sel]) - np.log(_cos_theta(P1, R1, u1, v)[sel])
    A = np.stack([np.ones_like(a), a], axis=1).astype(np.float64)
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    ids = (u[sel] // block).astype(np.int64) * 100_000 + (v[sel] // block).astype(np.int64)
    blocks = np.unique(ids)
    members = [np.flatnonzero(ids == b) for b in blocks]
    rng = np.random.default_rng(seed)
    boot = []
    for _ in range(bootstrap):
        idx = np.concatenate([members[k] for k in rng.integers(0, len(blocks), len(blocks))])
        boot.append(np.linalg.lstsq(A[idx], y[idx], rcond=None)[0][1])
    return VignettingFit(exponent=float(coef[1]), exponent_se=float(np.std(boot)),
                         log_gain_ratio=float(coef[0]), pixels=int(sel.sum()))
