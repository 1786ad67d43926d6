"""Vignetting: the lens passes less light to the image's edges than to its centre.

A pixel whose ray makes the angle ``theta`` with the optical axis receives ``cos(theta)^p``
of the light an on-axis pixel does (the natural falloff of a thin lens is ``p = 4``: the
cos^4 law; wide-angle designs and microlens arrays usually fall off less). With the
renderer's unit-z rays ``(x, y, 1)`` (undistorted normalised coordinates, so the lens's
distortion is accounted for), ``cos(theta) = 1 / sqrt(1 + x^2 + y^2)``.

:data:`EUROC_VIGNETTING` is EuRoC's, measured on the static micro slice's stereo pair
(``python experiments/camera_fit.py ../shared/data/euroc_v101_micro``,
:func:`uavcal_jax.sim.sensor_fit.stereo_vignetting`): p = 1.08 +- 0.07 over 141k matched
pixels (0.9-1.5 on the image's halves and on near or far surfaces alone). One camera's mean
image cannot give it: the scene's brightness varies across the image as much.
"""

from __future__ import annotations

__all__ = ["EUROC_VIGNETTING", "falloff"]

#: EuRoC's exponent ``p`` of ``cos(theta)^p`` (measured, above): 0.57 of the centre's light
#: in the corners of its 752x480 images (theta 53 degrees there, distortion undone), 0.68 at
#: the middle of the left and right edges.
EUROC_VIGNETTING = 1.1


def falloff(rx, ry, exponent: float):
    """``cos(theta)^exponent`` of rays ``(rx, ry, 1)`` (any matching shapes, numpy or jax)."""
    return (1.0 + rx * rx + ry * ry) ** (-0.5 * exponent)
