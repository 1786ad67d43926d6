"""The calibrator's loss, eq. 15-18 of Avola et al. (2023).

With ``o`` the true and ``o_hat`` the predicted offsets ``(B, C)`` and MSE the mean over
every window and channel::

    L_offset    = MSE(o_hat, o)                     (eq. 15)
    L_sign      = MSE(sign(o_hat), sign(o))         (eq. 16)
    L_magnitude = MSE(|o_hat|, |o|)                 (eq. 17)
    L           = L_offset + L_sign + L_magnitude   (eq. 18)

``sign`` is piecewise constant, so ``L_sign`` as written has **zero gradient almost
everywhere** (and none at 0): it adds to the reported loss but never moves the parameters.
``LossConfig.sign_term="tanh"`` replaces ``sign(o_hat)`` by the smooth surrogate
``tanh(o_hat / tau)``, which does push each prediction toward the true sign (most strongly
within ``tau`` of zero); the ablation compares the two. Offsets mix units (rad/s and m/s^2)
in one mean, as the paper does (``LossConfig.units="si"``); with ``units="standardized"`` the
offset and magnitude differences of channel ``c`` are divided by ``scale_c``, the standard
deviation of the offsets the protocol draws, so every channel weighs alike whatever its unit
and spread (under the raw mean a channel with a 10x smaller spread contributes 100x less
gradient, and the network learns it last).

A model with an uncertainty output (``ModelConfig.variance``) adds ``w_nll`` times
:func:`gaussian_nll`, the negative log-likelihood of the label under ``N(o_hat, sigma^2)``
per channel, with ``o_hat``'s gradient stopped: the uncertainty learns the estimate's error,
and the estimate learns exactly as eq. 18 alone would teach it.

A model with a tilt head (``ModelConfig.tilt_head``) adds ``w_tilt`` times
:func:`tilt_loss`, the auxiliary task of telling gravity's direction per frame.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uavcal_jax.calib.config import LossConfig

__all__ = ["calibration_loss", "gaussian_nll", "loss_terms", "tilt_loss"]


def _mse(a: jax.Array, b: jax.Array, weight: jax.Array | None,
         scale: jax.Array | None = None) -> jax.Array:
    sq = jnp.square(a - b if scale is None else (a - b) / scale)
    if weight is None:
        return jnp.mean(sq)
    w = jnp.broadcast_to(weight[:, None].astype(sq.dtype), sq.shape)
    return jnp.sum(sq * w) / jnp.maximum(jnp.sum(w), 1.0)


def loss_terms(pred: jax.Array, target: jax.Array, config: LossConfig | None = None,
               weight: jax.Array | None = None,
               scale: jax.Array | None = None) -> dict[str, jax.Array]:
    """The three terms of eq. 15-17, scalars, for ``pred``/``target`` ``(B, C)``.

    ``weight (B,)`` (optional, 0/1) leaves padded windows out of every mean. ``scale (C,)``
    divides the offset and magnitude differences (used when ``config.units`` is
    ``"standardized"``; ignored for ``"si"``). ``"sign"`` is
    the term the configured ``sign_term`` optimises (the surrogate when ``"tanh"``);
    ``"sign_exact"`` is always eq. 16 as written, for reporting.
    """
    config = LossConfig() if config is None else config
    pred = pred.astype(jnp.float32)
    target = target.astype(jnp.float32)
    scale = None if config.units == "si" or scale is None else scale.astype(jnp.float32)
    exact = _mse(jnp.sign(pred), jnp.sign(target), weight)
    if config.sign_term == "tanh":
        sign = _mse(jnp.tanh(pred / config.tau), jnp.sign(target), weight)
    else:
        sign = exact
    return {
        "offset": _mse(pred, target, weight, scale),
        "sign": sign,
        "magnitude": _mse(jnp.abs(pred), jnp.abs(target), weight, scale),
        "sign_exact": exact,
    }


def calibration_loss(pred: jax.Array, target: jax.Array, config: LossConfig | None = None,
                     weight: jax.Array | None = None, scale: jax.Array | None = None
                     ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 18: ``(loss, terms)``, ``loss = w_o L_offset + w_s L_sign + w_m L_magnitude``
    (weights 1 in the paper; ``config`` default :class:`LossConfig`); ``terms`` as
    :func:`loss_terms` (``scale``: see there)."""
    config = LossConfig() if config is None else config
    terms = loss_terms(pred, target, config, weight, scale)
    total = (config.w_offset * terms["offset"] + config.w_sign * terms["sign"]
             + config.w_magnitude * terms["magnitude"])
    return total, terms


def gaussian_nll(pred: jax.Array, log_sigma: jax.Array, target: jax.Array,
                 weight: jax.Array | None = None) -> jax.Array:
    """Mean over windows and channels of ``0.5 ((o - o_hat) / sigma)^2 + log sigma`` (the
    Gaussian negative log-likelihood less its constant), scalar, for ``pred``, ``log_sigma``
    and ``target`` ``(B, C)``; ``weight (B,)`` (0/1) leaves padded windows out. ``pred``'s
    gradient is stopped (see the module docstring)."""
    z = (target.astype(jnp.float32) - jax.lax.stop_gradient(pred.astype(jnp.float32))
         ) * jnp.exp(-log_sigma.astype(jnp.float32))
    term = 0.5 * jnp.square(z) + log_sigma.astype(jnp.float32)
    if weight is None:
        return jnp.mean(term)
    w = jnp.broadcast_to(weight[:, None].astype(term.dtype), term.shape)
    return jnp.sum(term * w) / jnp.maximum(jnp.sum(w), 1.0)


def tilt_loss(pred_up: jax.Array, up: jax.Array, mask: jax.Array,
              weight: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """``(loss, angle)``, scalars: the mean over labelled frames of ``|up_hat - up|^2`` and
    of the angle between them (degrees, for reporting), for the tilt head's ``pred_up`` and
    the true unit vectors ``up`` ``(B, T, 3)`` (a zero ``up`` marks a frame without ground
    truth), ``mask (B, T)`` the real frames and ``weight (B,)`` (0/1) the real windows."""
    up = up.astype(jnp.float32)
    pred_up = pred_up.astype(jnp.float32)
    labelled = jnp.asarray(mask, bool) & (jnp.sum(jnp.square(up), axis=-1) > 0.25)
    w = labelled.astype(jnp.float32)
    if weight is not None:
        w = w * weight.astype(jnp.float32)[:, None]
    total = jnp.maximum(jnp.sum(w), 1.0)
    loss = jnp.sum(w * jnp.sum(jnp.square(pred_up - up), axis=-1)) / total
    cos = jnp.sum(pred_up * up, axis=-1) / jnp.maximum(jnp.linalg.norm(pred_up, axis=-1), 1e-9)
    angle = jnp.degrees(jnp.arccos(jnp.clip(cos, -1.0, 1.0)))
    return loss, jnp.sum(w * angle) / total
