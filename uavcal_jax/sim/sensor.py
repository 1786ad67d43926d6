"""EuRoC's camera as a sensor: radiance -> electrons -> shot and read noise -> gain -> 8 bits.

The renderer returns a relative radiance ``L`` in [0, 1] per pixel. EuRoC's VI-sensor cameras
(Aptina MT9V034, global shutter, 8-bit output) turn the light of one exposure into a digital
number (DN) as

    electrons  lam = L * SCENE_ELECTRONS_PER_S * exposure_s     (mean photo-electrons)
    signal     e   = clip(lam + shot + read, 0, FULL_SCALE_ELECTRONS)  (shot: var lam; read:
                                                                  var READ_NOISE_ELECTRONS^2)
    DN         = clip(round(gain * e * 255 / FULL_SCALE_ELECTRONS), 0, 255)

so the mean brightness is a physical exposure x gain (a longer exposure or more gain makes the
image brighter, and gain amplifies the noise with it), not a histogram fit.

Where the constants come from. The 95 frames of ``euroc_v101_micro`` show the MAV standing
still, so the difference of consecutive frames is the sensor's temporal noise. Its variance
against the mean (a photon-transfer curve over both cameras, pixels with little local
gradient, 30-175 DN) is linear: ``var = 0.01496 DN * mean + 0.063 DN^2``. The slope is the
conversion gain at the recording's operating point, 66.9 electrons per DN, i.e. 255 DN =
17,050 e- (:data:`FULL_SCALE_ELECTRONS`, the recording's operating point taken as gain 1).
The intercept, 0.063 +- 0.045 DN^2, is at the quantisation floor (1/12 DN^2), so
the read noise is small: :data:`READ_NOISE_ELECTRONS` = 10 e- (0.15 DN, 0.022 DN^2) keeps the
model's floor within one standard error of it.

:data:`SCENE_ELECTRONS_PER_S`, the simulated hall's illumination as the sensor sees it, is
calibrated so that the default exposure (5 ms) and gain (1) give the real V1_01 frames' mean
intensity, 145.6 DN (cam0, 95 frames; std 52.9 DN, 10 % saturated), as the mean over the
scenes of flights along all 11 EuRoC trajectories (cam0 every 5 s over each full flight):
145.6 DN, from 127 (MH_02) to 170 (V1_03), scene-to-scene std 14 DN; pixel std 63 DN, 8 %
saturated. The renderer alone (``round(255 L)``) gives 45-65 DN on the same frames.
``tests/test_sim_camera.py`` checks a flight along V1_01 against the real frames.

Shot noise. Photo-electron counts are Poisson; they are drawn as ``N(lam, lam)``: the same
mean and variance, and the Poisson's skewness, ``1/sqrt(lam)``, is under 0.05 above 400 e-
(6 DN; a mid-grey pixel collects about 10,000 e-), where the two are indistinguishable after
rounding to DN. ``jax.random.poisson`` costs about
270 ms per 752x480 frame on this CPU, a Gaussian draw 7-12 ms. Shot and read noise are then
independent Gaussians, drawn as one of variance ``lam + read^2`` (the full-well clip after
both, rather than between them, differs only on saturated pixels, which read 255 at gain >= 1
either way).

All functions are pure and jit-able; randomness comes only from the key passed in.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import jax
import jax.numpy as jnp

__all__ = [
    "DN_MAX",
    "FULL_SCALE_ELECTRONS",
    "READ_NOISE_ELECTRONS",
    "SCENE_ELECTRONS_PER_S",
    "SensorModel",
    "ideal_image",
    "sensor_image",
]

#: 8-bit output (EuRoC's frames).
DN_MAX = 255
#: Electrons that fill the 8-bit range at gain 1 (measured conversion gain 0.01496 DN/e-).
FULL_SCALE_ELECTRONS = 17_050.0
#: Read noise, electrons rms (within the measured photon-transfer intercept's error).
READ_NOISE_ELECTRONS = 10.0
#: Photo-electrons per second collected from a surface the renderer shades at radiance 1.0;
#: calibrated once so the default exposure (5 ms) and gain (1) match V1_01's mean intensity.
SCENE_ELECTRONS_PER_S = 9.8e6


@dataclass(frozen=True)
class SensorModel:
    """A camera's photometric settings.

    Attributes:
        exposure_s: exposure (integration) time, seconds.
        gain: analog gain (1 = the measured V1_01 operating point).
        full_scale_electrons: electrons that fill ``0..DN_MAX`` at gain 1; also the clip of a
            pixel's charge (full well).
        read_noise_electrons: Gaussian read noise, electrons rms.
        scene_electrons_per_s: photo-electrons per second at rendered radiance 1.
    """

    exposure_s: float
    gain: float = 1.0
    full_scale_electrons: float = FULL_SCALE_ELECTRONS
    read_noise_electrons: float = READ_NOISE_ELECTRONS
    scene_electrons_per_s: float = SCENE_ELECTRONS_PER_S

    @property
    def dn_per_electron(self) -> float:
        """Conversion gain of the output, DN per electron (``gain * 255 / full scale``)."""
        return self.gain * DN_MAX / self.full_scale_electrons

    def mean_electrons(self, radiance):
        """Mean photo-electrons of an exposure for radiance ``L`` (any shape)."""
        return radiance * (self.scene_electrons_per_s * self.exposure_s)

    def mean_dn(self, radiance):
        """Noise-free DN before quantisation and clipping (the exposure x gain mapping)."""
        return self.mean_electrons(radiance) * self.dn_per_electron

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields plus the derived conversion gain (for ``sim_config.json``)."""
        return {**asdict(self), "dn_per_electron": self.dn_per_electron, "dn_max": DN_MAX,
                "shot_noise": "gaussian N(lam, lam) approximation of Poisson(lam)"}


def ideal_image(radiance: jax.Array) -> jax.Array:
    """The noise-free camera: ``round(255 L)`` as uint8 (any shape; ``L`` in [0, 1])."""
    return jnp.clip(jnp.round(radiance * 255.0), 0, DN_MAX).astype(jnp.uint8)


def sensor_image(radiance: jax.Array, key: jax.Array, model: SensorModel) -> jax.Array:
    """One exposure of radiance ``L`` (any shape, float, >= 0) -> uint8 DN of the same shape.

    Shot noise (variance = mean electrons) and read noise, the full-well clip, gain, rounding
    to the nearest DN and clipping to ``0..255``, as in the module docstring. ``key`` is a JAX PRNG
    key; the same key gives the same image.
    """
    f32 = jnp.float32
    lam = jnp.maximum(model.mean_electrons(radiance.astype(f32)), 0.0)
    sigma = jnp.sqrt(lam + f32(model.read_noise_electrons) ** 2)
    charge = jnp.clip(lam + sigma * jax.random.normal(key, lam.shape, f32), 0.0,
                      model.full_scale_electrons)
    dn = jnp.round(charge * f32(model.dn_per_electron))
    return jnp.clip(dn, 0, DN_MAX).astype(jnp.uint8)
