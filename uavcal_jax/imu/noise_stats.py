"""Noise statistics of an IMU signal: Allan deviation, the densities read off it, and the
power spectrum (rotor vibration).

All functions are pure numpy/scipy on one sensor's samples at a fixed rate: ``x`` is ``(N,)``
or ``(N, A)`` (A axes, e.g. a gyro's three), in the sensor's unit (rad/s or m/s^2), sampled
every ``dt`` seconds (``fs = 1 / dt`` Hz). To compare a real IMU with a simulated one during
motion, pass the *error* signal: the measurement minus the exact measurement of the ground
truth's motion (:func:`uavcal_jax.sim.imu_synth.synthesize_imu` without noise), so that the
motion itself does not dominate the statistics.

Allan deviation (IEEE Std 952, overlapping estimator): with ``theta_k = dt * sum_{i<k} x_i``
and a cluster of ``m`` samples (``tau = m dt``)::

    AVAR(tau) = sum_k (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2 / (2 tau^2 (N - 2m))

White noise of density ``q`` (unit/sqrt(Hz)) gives ``ADEV(tau) = q / sqrt(tau)``, a -1/2
slope on log-log axes; the flat bottom of the curve is the bias instability
``B = min ADEV / sqrt(2 ln 2 / pi)`` (``/ 0.664``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import trapezoid
from scipy.signal import welch

__all__ = [
    "BIAS_INSTABILITY_FACTOR",
    "VIBRATION_HZ",
    "allan_deviation",
    "allan_taus",
    "band_power",
    "bias_instability",
    "noise_summary",
    "peak_frequency",
    "power_spectral_density",
    "white_noise_density",
]

#: ``sqrt(2 ln 2 / pi)``: the flat part of the Allan deviation of flicker (1/f) bias noise is
#: this times the bias instability (IEEE Std 952, Annex C).
BIAS_INSTABILITY_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)

#: Power above this frequency counts as vibration: a drone's own motion is slower, and EuRoC's
#: MAV standing with its rotors running shows its largest peak at 19 Hz (in flight the rotors'
#: peaks alias to 90-100 Hz at the IMU's 200 Hz).
VIBRATION_HZ = 15.0


def _as_2d(x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or len(x) < 4 or not np.all(np.isfinite(x)):
        raise ValueError(f"expected finite (N,) or (N, A) samples with N >= 4, got shape "
                         f"{np.shape(x)}")
    return x


def allan_taus(n: int, dt: float, per_decade: int = 8) -> np.ndarray:
    """Cluster times (seconds) for :func:`allan_deviation`: ``m dt`` for distinct integer
    ``m`` spaced ``per_decade`` to a decade from 1 up to ``(n - 1) // 2`` (shape ``(T,)``)."""
    m_max = max((n - 1) // 2, 1)
    m = np.unique(np.round(np.logspace(0, np.log10(m_max), max(
        2, int(np.ceil(np.log10(m_max) * per_decade)) + 1))).astype(np.int64))
    return m * dt


def allan_deviation(x, dt: float, taus=None) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of a rate signal (see the module docstring).

    Args:
        x: (N,) or (N, A) samples (rate units: rad/s, m/s^2).
        dt: sample period, seconds.
        taus: cluster times in seconds (rounded to whole samples; default :func:`allan_taus`).

    Returns:
        ``(taus, adev)``: (T,) the cluster times used (whole multiples of ``dt``, at most
        ``(N - 1) / 2`` samples), and (T, A) the Allan deviation (same unit as ``x``;
        (T,) for a (N,) input).
    """
    squeeze = np.ndim(x) == 1
    x = _as_2d(x)
    n = len(x)
    if taus is None:
        taus = allan_taus(n, dt)
    m = np.unique(np.round(np.asarray(taus, np.float64) / dt).astype(np.int64))
    m = m[(m >= 1) & (2 * m <= n - 1)]
    if m.size == 0:
        raise ValueError(f"no cluster time fits in {n} samples of {dt:g} s")
    theta = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0) * dt])
    adev = np.empty((m.size, x.shape[1]))
    for i, mi in enumerate(m):
        d = theta[2 * mi:] - 2.0 * theta[mi:-mi] + theta[:-2 * mi]
        tau = mi * dt
        adev[i] = np.sqrt(np.mean(d * d, axis=0) / (2.0 * tau * tau))
    return m * dt, (adev[:, 0] if squeeze else adev)


def white_noise_density(taus, adev, tau_max: float = 1.0) -> np.ndarray:
    """White-noise density (unit/sqrt(Hz)) read off an Allan curve: ``ADEV(tau) sqrt(tau)``
    where the curve's log-log slope is closest to -1/2, among ``taus <= tau_max`` (IEEE 952's
    read-off of the -1/2 line at ``tau = 1 s``).

    Args:
        taus: (T,) seconds, increasing.
        adev: (T,) or (T, A) Allan deviation.
        tau_max: the longest cluster time considered, seconds.

    Returns:
        () or (A,) density.
    """
    taus = np.asarray(taus, np.float64)
    squeeze = np.ndim(adev) == 1
    adev = np.asarray(adev, np.float64).reshape(len(taus), -1)
    keep = taus <= tau_max
    if keep.sum() < 2:
        raise ValueError(f"need two cluster times <= {tau_max:g} s")
    lt, la = np.log(taus[keep]), np.log(adev[keep])
    slope = np.gradient(la, lt, axis=0)
    best = np.argmin(np.abs(slope + 0.5), axis=0)
    cols = np.arange(adev.shape[1])
    out = adev[keep][best, cols] * np.sqrt(taus[keep][best])
    return out[0] if squeeze else out


def bias_instability(adev) -> np.ndarray:
    """Bias instability (same unit as the signal): the Allan curve's minimum over its cluster
    times divided by :data:`BIAS_INSTABILITY_FACTOR`; () or (A,) for a (T,) or (T, A) curve."""
    return np.min(np.asarray(adev, np.float64), axis=0) / BIAS_INSTABILITY_FACTOR


#: Welch segment length (seconds) of :func:`power_spectral_density`: 0.25 Hz bins.
PSD_SEGMENT_S = 4.0
#: :func:`noise_summary` averages at least this many segments' lengths of samples (a short
#: span's segments are shortened): one Hann-windowed segment weighs the span's middle and
#: hides a vibration that changes over it (a MAV standing, its rotors starting and spooling).
MIN_SEGMENTS = 4


def power_spectral_density(x, fs: float, segment_s: float = PSD_SEGMENT_S
                           ) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density (Welch, Hann windows of ``segment_s`` seconds, half
    overlapping, each segment's mean removed).

    Args:
        x: (N,) or (N, A) samples.
        fs: sample rate, Hz.
        segment_s: segment length, seconds (shortened to N samples).

    Returns:
        ``(f, psd)``: (F,) Hz from 0 to ``fs / 2``, and (F,) or (F, A) in unit^2/Hz,
        one-sided (its integral over ``f`` is the variance): white noise of ``sensor.yaml``'s
        density ``q`` unit/sqrt(Hz) (discrete std ``q sqrt(fs)``) gives ``2 q^2``.
    """
    squeeze = np.ndim(x) == 1
    x = _as_2d(x)
    nperseg = int(min(len(x), max(8, round(segment_s * fs))))
    f, p = welch(x, fs=fs, nperseg=nperseg, axis=0, detrend="constant")
    return f, (p[:, 0] if squeeze else p)


def band_power(f, psd, f_lo: float, f_hi: float = np.inf) -> np.ndarray:
    """The power (unit^2, the variance) in ``f_lo <= f < f_hi``: the trapezoid integral of
    ``psd`` ((F,) or (F, A)) over those frequencies ``f`` (F,) Hz; () or (A,)."""
    f = np.asarray(f, np.float64)
    psd = np.asarray(psd, np.float64)
    keep = (f >= f_lo) & (f < f_hi)
    if keep.sum() < 2:
        raise ValueError(f"fewer than two frequencies in [{f_lo:g}, {f_hi:g}) Hz")
    return trapezoid(psd[keep], f[keep], axis=0)


def peak_frequency(f, psd, f_lo: float = 0.0) -> np.ndarray:
    """The frequency (Hz) of the spectrum's largest value at ``f >= f_lo`` (e.g. the rotors'
    vibration above the flight's motion); () or (A,) for (F,) or (F, A) ``psd``."""
    f = np.asarray(f, np.float64)
    psd = np.asarray(psd, np.float64)
    keep = f >= f_lo
    if not keep.any():
        raise ValueError(f"no frequency at or above {f_lo:g} Hz")
    return f[keep][np.argmax(psd[keep], axis=0)]


def noise_summary(x, dt: float, taus=(0.1, 1.0, 10.0), vibration_hz: float = VIBRATION_HZ
                  ) -> dict[str, float]:
    """One sensor's noise figures, each averaged over its axes.

    Args:
        x: (N, A) samples of one sensor (e.g. a gyro's error signal, rad/s), every ``dt`` s.
        dt: sample period, seconds.
        taus: cluster times (seconds) at which to report the Allan deviation.
        vibration_hz: the frequency above which power counts as vibration (rotors; a drone's
            own motion is slower).

    Returns:
        ``adev_<tau>s`` for each tau (the ``:g`` format of tau; unit of ``x``),
        ``white_density`` (unit/sqrt(Hz), :func:`white_noise_density`), ``bias_instability``
        (unit), ``vibration_rms`` (unit: the square root of the power above ``vibration_hz``
        summed over the axes) and ``peak_hz`` (the largest peak of the axes' summed spectrum
        above ``vibration_hz``); the spectrum's segments are :data:`PSD_SEGMENT_S` long, or
        a :data:`MIN_SEGMENTS`-th of a shorter span.
    """
    x = _as_2d(x)
    all_taus, adev = allan_deviation(x, dt)
    out = {}
    for tau in taus:
        _, at = allan_deviation(x, dt, [tau])
        out[f"adev_{tau:g}s"] = float(at.mean())
    out["white_density"] = float(white_noise_density(all_taus, adev).mean())
    out["bias_instability"] = float(bias_instability(adev).mean())
    f, p = power_spectral_density(x, 1.0 / dt, min(PSD_SEGMENT_S, len(x) * dt / MIN_SEGMENTS))
    total = p.sum(axis=1)
    out["vibration_rms"] = float(np.sqrt(band_power(f, total, vibration_hz)))
    out["peak_hz"] = float(peak_frequency(f, total, vibration_hz))
    return out
