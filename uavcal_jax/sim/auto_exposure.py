"""Auto-exposure: the exposure and gain of each frame, as a camera's controller sets them.

A real auto-exposure (AE) meters each frame's mean intensity and moves the next frame's
brightness (exposure x gain) toward a target, low-pass filtered so that it does not hunt: when
the scene brightens (a lamp, a window, a white wall) the frame steps brighter and recovers over
a few frames. :func:`exposure_schedule` is that controller, a first-order loop in log
brightness with one frame of latency:

    b_k = exposure_k * gain_k
    m_k = mean over the metering image of clip(V L_k * b_k * c, 0, 255)    (noise-free DN)
    log b_{k+1} = log b_k + alpha * log(target / m_k),   alpha = 1 - exp(-dt / tau)

(``c`` converts radiance x seconds x gain to DN, :meth:`SensorModel.mean_dn`; ``V`` the
vignetting). Unsaturated, the log error after a brightness step decays as ``exp(-t / tau)``.
Brightness goes to the exposure first, up to :data:`MAX_EXPOSURE_S`, then to the gain up to
:data:`MAX_GAIN` (the MT9V034's analog range is 1x-4x); the loop's state is the brightness it
could realise, so it does not wind up at the limits.

The metering image is a low-resolution render (:data:`METERING_SCALE` of the frame's size):
the mean of a 94x60 render is the mean of the full frame within a fraction of a DN, and a real
AE meters on a coarse histogram too. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uavcal_jax.sim.sensor import DN_MAX, SensorModel

__all__ = [
    "AE_TARGET_DN",
    "AE_TIME_CONSTANT_S",
    "MAX_EXPOSURE_S",
    "MAX_GAIN",
    "METERING_SCALE",
    "MIN_EXPOSURE_S",
    "AutoExposure",
    "exposure_schedule",
    "metered_dn",
]

#: EuRoC-like AE target: V1_01's real cam0 mean intensity over the micro slice, DN.
AE_TARGET_DN = 145.6
#: AE time constant, seconds (3 frames at 20 Hz: a typical AE settles in 3-10 frames; the
#: static micro slice cannot show EuRoC's own).
AE_TIME_CONSTANT_S = 0.15
#: Longest exposure the AE uses, seconds (EuRoC's indoor exposures are about 1-10 ms).
MAX_EXPOSURE_S = 10e-3
#: Shortest exposure, seconds.
MIN_EXPOSURE_S = 50e-6
#: Highest analog gain (MT9V034: 1x-4x).
MAX_GAIN = 4.0
#: Metering render size as a fraction of the frame's.
METERING_SCALE = 0.125


@dataclass(frozen=True)
class AutoExposure:
    """The controller's settings.

    Attributes:
        target_dn: mean intensity the loop drives toward, DN.
        time_constant_s: first-order time constant of the loop, seconds.
        max_exposure_s, min_exposure_s: exposure range, seconds.
        max_gain: gain range is ``[1, max_gain]``.
        start_settled: the first frame's settings are those the loop settles at on it (a
            camera that ran before the recording began, as EuRoC's); ``False``: the
            sensor's own exposure and gain, the loop converging from there.
    """

    target_dn: float = AE_TARGET_DN
    time_constant_s: float = AE_TIME_CONSTANT_S
    max_exposure_s: float = MAX_EXPOSURE_S
    min_exposure_s: float = MIN_EXPOSURE_S
    max_gain: float = MAX_GAIN
    start_settled: bool = True


#: Full steps the loop takes on the first frame to settle (clipped metering converges
#: geometrically; a few steps reach the target to well under a DN).
SETTLE_STEPS = 30


def _split(brightness: float, ae: AutoExposure) -> tuple[float, float]:
    """Exposure (s) and gain realising ``brightness`` (s x gain) within the limits."""
    exposure = min(max(brightness, ae.min_exposure_s), ae.max_exposure_s)
    gain = min(max(brightness / exposure, 1.0), ae.max_gain)
    return exposure, gain


def metered_dn(radiance: np.ndarray, exposure_s: float, gain: float,
               model: SensorModel) -> float:
    """The AE's meter: mean noise-free DN, clipped to ``0..255``, of ``radiance`` (any shape,
    already vignetted) at this exposure and gain."""
    scale = model.scene_electrons_per_s * exposure_s * gain * DN_MAX / model.full_scale_electrons
    return float(np.clip(np.asarray(radiance, np.float64) * scale, 0.0, DN_MAX).mean())


def exposure_schedule(metering: np.ndarray, dt_s: np.ndarray | float, model: SensorModel,
                      ae: AutoExposure) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame exposure and gain chosen by the AE loop.

    Args:
        metering: (N, ...) each frame's metering radiance (a low-resolution render, vignetted).
        dt_s: seconds from each frame to the next, scalar or (N - 1,).
        model: the sensor; its ``exposure_s`` and ``gain`` are where the loop starts (the
            first frame's unless ``ae.start_settled``).
        ae: the controller's settings.

    Returns:
        ``(exposure_s (N,), gain (N,))``: frame ``k``'s settings, chosen from frames ``< k``.
    """
    n = int(np.shape(metering)[0])
    dt = np.broadcast_to(np.asarray(dt_s, np.float64), (max(n - 1, 0),))
    exposure, gain = np.zeros(n), np.zeros(n)
    e, g = _split(model.exposure_s * model.gain, ae)
    for _ in range(SETTLE_STEPS if ae.start_settled and n else 0):
        step = np.log(ae.target_dn / max(metered_dn(metering[0], e, g, model), 1.0))
        if abs(step) < 1e-6:
            break
        e, g = _split(e * g * np.exp(step), ae)
    for k in range(n):
        exposure[k], gain[k] = e, g
        if k + 1 < n:
            m = max(metered_dn(metering[k], e, g, model), 1.0)  # a black frame: full step up
            alpha = 1.0 - np.exp(-dt[k] / ae.time_constant_s)
            e, g = _split(e * g * np.exp(alpha * np.log(ae.target_dn / m)), ae)
    return exposure, gain
