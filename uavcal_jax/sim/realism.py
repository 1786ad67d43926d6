"""Image statistics that compare rendered frames with real ones (``experiments/sim_realism.py``).

Pure numpy functions on 8-bit gray frames: ``frames`` is a (T, H, W) uint8 stack (or a
sequence of (H, W) images) of one camera, intensities in grey levels 0-255. Each returns a
few numbers that a realistic simulator must match: the intensity distribution, the gradient
distribution (texture and sharpness), and the temporal noise of a static camera.

:func:`imu_errors` gives the IMU's side: the error signal (measurement minus the exact
measurement of the ground truth's motion) of a real IMU and of the simulator's IMU over the
same flight, for :mod:`uavcal_jax.imu.noise_stats`.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.data.sequence import GroundTruth, ImuData
from uavcal_jax.imu.noise import ImuNoise
from uavcal_jax.sim.imu_synth import synthesize_imu
from uavcal_jax.sim.trajectory_fit import fit_tum_trajectory

__all__ = [
    "GRADIENT_PERCENTILES",
    "INTENSITY_PERCENTILES",
    "gradient_magnitude",
    "gradient_summary",
    "histogram_emd",
    "imu_errors",
    "intensity_histogram",
    "intensity_summary",
    "photon_transfer",
    "temporal_noise",
]

#: Percentiles that summarise the intensity distribution.
INTENSITY_PERCENTILES = (5, 50, 95)
#: Percentiles that summarise the gradient-magnitude distribution.
GRADIENT_PERCENTILES = (50, 90)


def _stack(frames) -> np.ndarray:
    stack = np.asarray(frames)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3 or stack.size == 0:
        raise ValueError(f"expected (T, H, W) gray frames, got shape {stack.shape}")
    return stack.astype(np.float64)


def intensity_histogram(frames) -> np.ndarray:
    """(256,) the fraction of pixels at each grey level 0..255 over all ``frames`` (sums to 1)."""
    stack = np.clip(np.rint(_stack(frames)), 0, 255).astype(np.int64)
    counts = np.bincount(stack.ravel(), minlength=256).astype(np.float64)
    return counts / counts.sum()


def intensity_summary(frames) -> dict[str, float]:
    """``mean``, ``std`` and ``p5``/``p50``/``p95`` (:data:`INTENSITY_PERCENTILES`) of the
    pixel intensities of all ``frames``, grey levels; ``saturated``: the fraction of pixels at
    0 or 255."""
    stack = _stack(frames)
    out = {"mean": float(stack.mean()), "std": float(stack.std())}
    for q, v in zip(INTENSITY_PERCENTILES, np.percentile(stack, INTENSITY_PERCENTILES),
                    strict=True):
        out[f"p{q}"] = float(v)
    out["saturated"] = float(np.mean((stack <= 0) | (stack >= 255)))
    return out


def histogram_emd(h0, h1) -> float:
    """Earth mover's distance between two intensity histograms ((256,) each, any positive
    scale): the grey levels one distribution's pixels move on average to become the other
    (``sum |CDF0 - CDF1|``; 0 for equal distributions, ``|a - b|`` for two single levels)."""
    h0 = np.asarray(h0, np.float64)
    h1 = np.asarray(h1, np.float64)
    if h0.shape != h1.shape or h0.ndim != 1:
        raise ValueError(f"histograms of different shapes: {h0.shape} and {h1.shape}")
    return float(np.abs(np.cumsum(h0 / h0.sum()) - np.cumsum(h1 / h1.sum())).sum())


def gradient_magnitude(image) -> np.ndarray:
    """(H-2, W-2) gradient magnitude, grey levels per pixel: central differences
    ``sqrt(((I[x+1] - I[x-1]) / 2)^2 + ((I[y+1] - I[y-1]) / 2)^2)`` on the interior pixels of
    an (H, W) image."""
    img = np.asarray(image, np.float64)
    if img.ndim != 2 or min(img.shape) < 3:
        raise ValueError(f"expected an (H, W) image at least 3x3, got shape {img.shape}")
    gx = 0.5 * (img[1:-1, 2:] - img[1:-1, :-2])
    gy = 0.5 * (img[2:, 1:-1] - img[:-2, 1:-1])
    return np.hypot(gx, gy)


def gradient_summary(frames) -> dict[str, float]:
    """``mean`` and ``p50``/``p90`` (:data:`GRADIENT_PERCENTILES`) of the gradient magnitude
    (:func:`gradient_magnitude`, grey levels per pixel) over all ``frames``."""
    grads = np.stack([gradient_magnitude(f) for f in _stack(frames)])
    out = {"mean": float(grads.mean())}
    for q, v in zip(GRADIENT_PERCENTILES, np.percentile(grads, GRADIENT_PERCENTILES),
                    strict=True):
        out[f"p{q}"] = float(v)
    return out


def _flat_pixels(stack: np.ndarray, flat_quantile: float, margin: float):
    """(mean, std, keep) of the interior pixels of a static (T, H, W) stack: the flat,
    unclipped ones (see :func:`temporal_noise`)."""
    if len(stack) < 2:
        raise ValueError("temporal noise needs at least two frames")
    mean = stack.mean(axis=0)[1:-1, 1:-1]
    std = stack.std(axis=0, ddof=1)[1:-1, 1:-1]
    grad = gradient_magnitude(stack.mean(axis=0))
    keep = (grad <= np.quantile(grad, flat_quantile)) & (mean > margin) & (mean < 255 - margin)
    if not keep.any():
        raise ValueError("no flat, unclipped pixels to measure the noise on")
    return mean, std, keep


def temporal_noise(frames, flat_quantile: float = 0.5, margin: float = 5.0) -> dict[str, float]:
    """Image noise of a static camera: the per-pixel standard deviation over time.

    The camera must not move (or under a pixel): a pixel's variation over time is then the
    sensor's noise. Only flat, unclipped pixels count: those where the mean image's gradient
    magnitude is at most its ``flat_quantile`` quantile (a sub-pixel shake changes pixels at
    edges far more than the noise does) and whose mean lies within ``margin`` grey levels of
    neither 0 nor 255 (clipping hides noise).

    Args:
        frames: (T, H, W) gray frames of one camera, T >= 2.
        flat_quantile: the fraction of the flattest pixels considered.
        margin: grey levels kept away from the clip levels.

    Returns:
        ``std_median``: the median per-pixel temporal std (grey levels, ddof 1);
        ``std_mean``; ``mean_level``: the mean intensity of the pixels counted.
    """
    mean, std, keep = _flat_pixels(_stack(frames), flat_quantile, margin)
    return {"std_median": float(np.median(std[keep])), "std_mean": float(std[keep].mean()),
            "mean_level": float(mean[keep].mean())}


#: Grey levels (DN) where EuRoC's cameras respond linearly, as :mod:`uavcal_jax.sim.sensor`'s
#: photon-transfer fit took them: below, the black-level clip; above, saturation shrinks the
#: variance and bends the line (fitted over 0-255, the real cam0's intercept is 0.35 DN^2 and
#: cam1's -7 DN^2).
LINEAR_RANGE_DN = (30.0, 175.0)


def photon_transfer(frames, bins: int = 16, min_pixels: int = 50, flat_quantile: float = 0.5,
                    margin: float = 5.0, levels: tuple[float, float] = LINEAR_RANGE_DN
                    ) -> dict[str, float]:
    """The photon transfer line of a static camera: temporal variance against mean level.

    A sensor with shot and read noise has ``var = read^2 + shot * level`` (grey levels^2;
    ``shot`` is the grey levels one photo-electron adds, times the gain), so the line tells
    the two apart where one noise figure at one level cannot. The flat, unclipped pixels of
    :func:`temporal_noise` whose mean level lies in ``levels`` (DN) are binned by it
    (``bins`` equal bins over 0-255, those with at least ``min_pixels`` pixels kept), and the
    line is fitted by least squares to the bins' median variances.

    Returns:
        ``read_noise``: grey levels (the square root of the intercept, 0 when it is
        negative); ``shot_slope``: grey levels^2 of variance per grey level of signal;
        ``levels``: how many bins the fit used (at least two, else both figures are NaN).
    """
    mean, std, keep = _flat_pixels(_stack(frames), flat_quantile, margin)
    keep &= (mean >= levels[0]) & (mean < levels[1])
    level, var = mean[keep], std[keep] ** 2
    idx = np.minimum((level / 256.0 * bins).astype(np.int64), bins - 1)
    xs, ys = [], []
    for b in range(bins):
        inside = idx == b
        if inside.sum() >= min_pixels:
            xs.append(np.median(level[inside]))
            ys.append(np.median(var[inside]))
    if len(xs) < 2:
        return {"read_noise": float("nan"), "shot_slope": float("nan"), "levels": len(xs)}
    slope, intercept = np.polyfit(np.asarray(xs), np.asarray(ys), 1)
    return {"read_noise": float(np.sqrt(max(intercept, 0.0))), "shot_slope": float(slope),
            "levels": len(xs)}


def imu_errors(ground_truth: GroundTruth, imu: ImuData, noise: ImuNoise, seed: int = 0,
               **sensor_errors) -> dict[str, np.ndarray]:
    """The error signals of a real IMU and of the simulator's IMU along the same flight.

    A smooth trajectory is fitted to the ground truth
    (:func:`~uavcal_jax.sim.trajectory_fit.fit_tum_trajectory`; its body frame must be the
    IMU frame, as EuRoC's); its exact measurements at the real IMU's timestamps are
    subtracted from the real samples and from the simulator's
    (:func:`~uavcal_jax.sim.imu_synth.synthesize_imu` with ``noise`` and ``seed``: white
    noise, bias random walk and turn-on bias). Motion the fit does not follow (above a few Hz
    at EuRoC's 20 Hz ground truth) stays in the real error: that is the real sensor's
    vibration, and at low frequencies also the fit's own error.

    Args:
        ground_truth: the flight's poses (body = IMU frame).
        imu: the real IMU samples; those inside the ground truth's span are used.
        noise: the simulator's IMU noise model.
        seed: the simulator's IMU noise seed.
        sensor_errors: the simulated sensor's errors beyond its noise, as
            :func:`~uavcal_jax.sim.imu_synth.synthesize_imu` takes them (``vibration``,
            ``vibration_scale``, ``intrinsics``, ``time_offset``;
            :func:`uavcal_jax.sim.simulate.imu_error_options` of a ``SimConfig``).

    Returns:
        ``t_ns`` (N,) int64; ``real`` and ``sim``: (N, 6) errors, gyro rad/s xyz then accel
        m/s^2 xyz, in the IMU frame.
    """
    traj = fit_tum_trajectory(ground_truth)
    t_ns = np.asarray(imu.t_ns, np.int64)
    inside = (t_ns >= int(np.ceil(traj.t_start * 1e9))) & (t_ns <= int(traj.t_end * 1e9))
    if inside.sum() < 4:
        raise ValueError("fewer than 4 IMU samples inside the ground truth's span")
    t_ns = t_ns[inside]
    exact = synthesize_imu(traj, t_ns=t_ns).imu
    sim = synthesize_imu(traj, noise=noise, seed=seed, t_ns=t_ns, **sensor_errors).imu
    real = np.concatenate([imu.gyro[inside], imu.accel[inside]], axis=1)
    ref = np.concatenate([exact.gyro, exact.accel], axis=1)
    return {"t_ns": t_ns, "real": real - ref,
            "sim": np.concatenate([sim.gyro, sim.accel], axis=1) - ref}
