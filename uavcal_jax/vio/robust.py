"""Robust functions ``rho(s)`` of a squared whitened residual ``s`` (RPEOD eq. 9) and their
derivatives, in Ceres' convention: the cost of a block is ``0.5 rho(s)``, its gradient
``rho'(s) J^T r``, and the IRLS (Gauss-Newton) Hessian ``rho'(s) J^T J``.

With scale ``a``:

* ``"huber"``: ``rho = s`` for ``s <= a^2``, ``2 a sqrt(s) - a^2`` beyond (RPEOD eq. 9 and the
  VINS-Mono paper, ``a = 1``): quadratic near zero, linear in the error beyond ``a`` sigmas,
  so one gross outlier pulls the solution with a bounded force.
* ``"cauchy"``: ``rho = a^2 log(1 + s / a^2)`` (VINS-Fusion's ``CauchyLoss(1.0)``): the pull
  of an outlier decreases with its size.
* ``"none"``: ``rho = s``.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["equivalent_scale", "rho", "weight"]


def rho(s, kernel: str, scale: float = 1.0):
    """``rho(s)`` (...) for squared residuals ``s >= 0`` (...)."""
    a2 = scale * scale
    if kernel == "none":
        return s
    if kernel == "huber":
        big = s > a2
        root = jnp.sqrt(jnp.where(big, s, a2))
        return jnp.where(big, 2.0 * scale * root - a2, s)
    if kernel == "cauchy":
        return a2 * jnp.log1p(s / a2)
    raise ValueError(f"unknown robust kernel {kernel!r}")


def weight(s, kernel: str, scale: float = 1.0):
    """``rho'(s)`` (...): the IRLS weight of the block (its square root scales ``r``, ``J``)."""
    a2 = scale * scale
    if kernel == "none":
        return jnp.ones_like(s)
    if kernel == "huber":
        big = s > a2
        return jnp.where(big, scale / jnp.sqrt(jnp.where(big, s, a2)), 1.0)
    if kernel == "cauchy":
        return 1.0 / (1.0 + s / a2)
    raise ValueError(f"unknown robust kernel {kernel!r}")


def equivalent_scale(s, kernel: str, scale: float = 1.0):
    """``sqrt(rho(s) / s)`` (...): ``r`` times it has squared norm ``rho(s)``, so a plain
    least-squares solver (jaxopt) minimises the same robust cost. 1 at ``s = 0``."""
    if kernel == "none":
        return jnp.ones_like(s)
    tiny = s < 1e-30
    s_safe = jnp.where(tiny, 1.0, s)
    return jnp.where(tiny, 1.0, jnp.sqrt(rho(s_safe, kernel, scale) / s_safe))
