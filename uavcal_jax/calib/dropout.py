"""Dropout whose masks come from a counter hash instead of one threefry draw per element.

Why: the calibrator's training step drops out about 180 million activations (every frame's
patch tokens, attention weights and feed-forward hidden units, 3,200 frames per paper batch).
``flax.linen.Dropout`` draws each mask element with ``jax.random.bernoulli``: one threefry-2x32
evaluation (20 rounds) per element, which on XLA:CPU cost about a quarter of the whole step
(measured: 3.10 s against 2.35 s without dropout, paper model, batch 4). Here one threefry
draw per call gives two 32-bit seeds, and each element's 32 random bits are a two-round
``lowbias32`` integer hash (Wellons' constants; full avalanche, every output bit flips with
probability 1/2 for any input bit) of its flat index mixed with the seeds: a handful of
integer operations per element, elementwise on an iota, so it vectorises, shards and vmaps
like any elementwise op (the data-parallel step still draws what the one-device step draws).

What is kept: Bernoulli(1 - rate) masks, independent across calls (keys) and, to the
resolution tests can see, across elements; the inverted-dropout scaling by ``1 / (1 - rate)``;
``rate`` quantised to 2^-32. What is not: bit-equality with ``flax.linen.Dropout``'s stream
(not a property any result depends on).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Dropout", "attention", "dropout", "hash_bits", "keep_mask"]

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)


def _lowbias32(x: jax.Array) -> jax.Array:
    x = x ^ (x >> 16)
    x = x * _M1
    x = x ^ (x >> 15)
    x = x * _M2
    return x ^ (x >> 16)


def hash_bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """``uint32`` random bits of ``shape`` from ``key`` (one threefry draw for the seeds)."""
    seed = jax.random.bits(key, (2,), jnp.uint32)
    index = jax.lax.iota(jnp.uint32, int(np.prod(shape, dtype=np.int64))).reshape(shape)
    return _lowbias32(_lowbias32(index ^ seed[0]) + seed[1])


def keep_mask(key: jax.Array, shape: tuple[int, ...], rate: float) -> jax.Array:
    """Boolean mask of ``shape``, each element ``True`` with probability ``1 - rate``."""
    threshold = np.uint32(min(round(float(rate) * 2.0**32), 2**32 - 1))
    return hash_bits(key, shape) >= threshold


def dropout(x: jax.Array, rate: float, key: jax.Array) -> jax.Array:
    """Inverted dropout of ``x``: elements zeroed with probability ``rate``, the rest scaled
    by ``1 / (1 - rate)``."""
    if rate <= 0.0:
        return x
    if rate >= 1.0:
        return jnp.zeros_like(x)
    keep = keep_mask(key, x.shape, rate)
    return jnp.where(keep, x / jnp.asarray(1.0 - rate, x.dtype), jnp.zeros((), x.dtype))


class Dropout(nn.Module):
    """Drop-in for ``flax.linen.Dropout(rate)`` on the ``"dropout"`` rng stream."""

    rate: float

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        if deterministic or self.rate <= 0.0:
            return x
        return dropout(x, self.rate, self.make_rng("dropout"))


def attention(query, key, value, mask=None, dropout_rng=None, dropout_rate: float = 0.0,
              deterministic: bool = True, dtype=None, precision=None):
    """``flax.linen.dot_product_attention`` (per-element dropout on the attention weights,
    ``broadcast_dropout=False``) with :func:`dropout`'s masks; for
    ``MultiHeadDotProductAttention(attention_fn=...)``. Shapes ``(..., length, heads, d)``.

    The weights and their softmax are computed in the type of ``query``/``key`` (float32
    in the calibrator), whatever ``dtype`` the attention module computes its projections
    in: ``dtype`` is accepted for the ``attention_fn`` interface and not used."""
    del dtype
    weights = nn.dot_product_attention_weights(query, key, mask=mask, deterministic=True,
                                               precision=precision)
    if not deterministic and dropout_rate > 0.0:
        weights = dropout(weights, dropout_rate, dropout_rng)
    return jnp.einsum("...hqk,...khd->...qhd", weights, value, precision=precision)
