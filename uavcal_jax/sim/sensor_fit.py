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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ESTIMATORS", "NoiseCurve", "ShotReadFit", "fit_shot_read", "noise_curve",
           "temporal_variance"]

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
