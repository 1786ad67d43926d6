"""Vignetting: the lens passes less light to the image's edges than to its centre.

A pixel whose ray makes the angle ``theta`` with the optical axis receives ``cos(theta)^p``
of the light an on-axis pixel does (the natural falloff of a thin lens is ``p = 4``: the
cos^4 law; wide-angle designs and microlens arrays usually fall off less). With the
renderer's unit-z rays ``(x, y, 1)`` (undistorted normalised coordinates, so the lens's
distortion is accounted for), ``cos(theta) = 1 / sqrt(1 + x^2 + y^2)``.

:data:`EUROC_VIGNETTING` is the EuRoC-like exponent. The micro slice's radial mean-intensity
profile bounds it (the scene is confounded with the falloff, but not that much): the outer
ring (undistorted radius 0.9-1.0, 4 % of the pixels) is 0.85-1.0 times the centre disc's
brightness in both cameras, where cos^4 would give 0.28; see ``uavcal_jax.sim.config``'s
preset for the command.
"""

from __future__ import annotations

__all__ = ["EUROC_VIGNETTING", "falloff"]

#: EuRoC-like exponent ``p`` of ``cos(theta)^p``: about 0.8 of the centre's light in the
#: corners of EuRoC's 752x480 lens (theta about 51 degrees there, distortion undone).
EUROC_VIGNETTING = 0.5


def falloff(rx, ry, exponent: float):
    """``cos(theta)^exponent`` of rays ``(rx, ry, 1)`` (any matching shapes, numpy or jax)."""
    return (1.0 + rx * rx + ry * ry) ** (-0.5 * exponent)
