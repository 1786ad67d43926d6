"""Transformer encoder and decoder stacks of the calibrator (paper section 3, "TE"/"TD").

Each layer is the standard one of Vaswani et al. as PyTorch's ``nn.TransformerEncoderLayer``
/ ``nn.TransformerDecoderLayer`` build it (the paper's implementation): multi-head attention,
a two-layer feed-forward block ``Linear -> activation -> dropout -> Linear``, residual
dropout, and layer norms after each residual sum (post-norm; ``norm_first`` moves them in
front). Stacks have no final norm (PyTorch's default ``norm=None``). All float32, except that
an :class:`Encoder` built with ``dtype=jnp.bfloat16`` (the frame encoder under
``ModelConfig.frame_encoder_dtype``) rounds the operands of its matrix products to bfloat16
and accumulates them in float32 (:func:`dot_general_for`).

Initialisation follows PyTorch's (what the paper's model starts from), which also compiles
far faster on CPU than Flax's truncated-normal default: linear and convolution kernels
``U(-1/sqrt(fan_in), 1/sqrt(fan_in))`` (``nn.Linear``'s Kaiming-uniform with ``a = sqrt(5)``),
attention input projections Xavier-uniform, attention biases zero. Other biases start at
zero (PyTorch draws them from the kernel's interval).

Masks are boolean ``(B, n)`` *key* masks, ``True`` on tokens that exist: attention gives
padded tokens zero weight, so their content never reaches a real token.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.calib.config import ModelConfig
from uavcal_jax.calib.dropout import Dropout, attention

__all__ = ["ACTIVATION_FNS", "LINEAR_INIT", "Decoder", "Encoder", "dot_general_for", "key_mask"]

F32 = jnp.float32

# U(-1/sqrt(fan_in), 1/sqrt(fan_in)): variance scaling by 1/3 with a uniform draw.
LINEAR_INIT = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")

ACTIVATION_FNS = {"relu": nn.relu, "gelu": nn.gelu}


def _scaled_dot_general(lhs, rhs, dimension_numbers, precision=None, *, scale=None):
    out = jax.lax.dot_general(lhs, rhs, dimension_numbers, precision=precision,
                              preferred_element_type=F32)
    return out if scale is None else out * F32(scale)


def dot_general_for(dtype, scale: float | None = None):
    """The ``dot_general`` of a flax ``Dense(dtype=dtype)``: ``None`` (flax's own) for
    float32 without ``scale``; otherwise the product of the ``dtype`` operands accumulated
    and returned in float32 (so only the operands are rounded, not the sums), times
    ``scale`` when given."""
    if jnp.dtype(dtype) == F32 and scale is None:
        return None
    return functools.partial(_scaled_dot_general, scale=scale)


def key_mask(query_len: int, key_valid: jax.Array | None) -> jax.Array | None:
    """Attention mask ``(B, 1, query_len, n)`` from a key mask ``(B, n)`` (``None`` passes)."""
    if key_valid is None:
        return None
    key_valid = key_valid.astype(bool)
    return jnp.broadcast_to(key_valid[:, None, None, :],
                            (key_valid.shape[0], 1, query_len, key_valid.shape[1]))


class FeedForward(nn.Module):
    """``Linear(d, ff) -> activation -> dropout -> Linear(ff, d)`` on (..., d)."""

    config: ModelConfig
    dtype: jnp.dtype = F32

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool) -> jax.Array:
        c = self.config
        dense = functools.partial(nn.Dense, dtype=self.dtype, param_dtype=F32,
                                  kernel_init=LINEAR_INIT,
                                  dot_general=dot_general_for(self.dtype))
        x = dense(c.ff_width, name="linear1")(x)
        x = ACTIVATION_FNS[c.activation](x)
        x = Dropout(c.dropout)(x, deterministic=deterministic)
        return dense(c.d_model, name="linear2")(x)


def _attention(c: ModelConfig, name: str, dtype=F32) -> nn.MultiHeadDotProductAttention:
    # the projections may run in bfloat16 (float32 results); the attention weights and
    # their softmax are float32 whatever ``dtype`` (:func:`attention` ignores it)
    return nn.MultiHeadDotProductAttention(
        num_heads=c.heads, qkv_features=c.d_model, out_features=c.d_model,
        dropout_rate=c.dropout, broadcast_dropout=False, dtype=dtype, param_dtype=F32,
        kernel_init=nn.initializers.xavier_uniform(), out_kernel_init=LINEAR_INIT,
        qkv_dot_general=dot_general_for(dtype), out_dot_general=dot_general_for(dtype),
        attention_fn=attention, name=name)


def _norm(c: ModelConfig, name: str) -> nn.LayerNorm:
    return nn.LayerNorm(epsilon=c.layer_norm_eps, dtype=F32, param_dtype=F32, name=name)


class EncoderLayer(nn.Module):
    """Self-attention + feed-forward on tokens ``(B, n, d)`` with key mask ``(B, n)``.

    ``outputs``: compute only the first ``outputs`` rows of the result (``None``: all). Each
    output row depends on all tokens through attention's keys and values, but the rest of
    the layer (query, feed-forward, norms) is per row, so a caller that reads only the
    first row of the last layer (the frame encoder's frame token) skips the others' cost:
    the same numbers, about 40 % fewer operations in the frame encoder.

    ``dtype``: operand type of the matrix products (see :func:`dot_general_for`).
    """

    config: ModelConfig
    dtype: jnp.dtype = F32

    @nn.compact
    def __call__(self, x, valid, deterministic: bool, outputs: int | None = None):
        c = self.config
        drop = Dropout(c.dropout)
        attn = _attention(c, "self_attn", self.dtype)
        ff = FeedForward(c, self.dtype, name="ff")
        n1, n2 = _norm(c, "norm1"), _norm(c, "norm2")
        rows = slice(None) if outputs is None else slice(0, outputs)
        mask = key_mask(x[:, rows].shape[1], valid)

        def sa(query, keys):
            return drop(attn(query, keys, mask=mask, deterministic=deterministic),
                        deterministic=deterministic)

        def fb(y):
            return drop(ff(y, deterministic), deterministic=deterministic)

        if c.norm_first:
            y = n1(x)
            x = x[:, rows] + sa(y[:, rows], y)
            return x + fb(n2(x))
        x = n1(x[:, rows] + sa(x[:, rows], x))
        return n2(x + fb(x))


class DecoderLayer(nn.Module):
    """Self-attention on the target, cross-attention to ``memory`` (key mask ``(B, m)``),
    feed-forward; target ``(B, q, d)``, memory ``(B, m, d)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, x, memory, memory_valid, deterministic: bool):
        c = self.config
        drop = Dropout(c.dropout)
        self_attn, cross_attn = _attention(c, "self_attn"), _attention(c, "cross_attn")
        ff = FeedForward(c, name="ff")
        n1, n2, n3 = _norm(c, "norm1"), _norm(c, "norm2"), _norm(c, "norm3")
        mask = key_mask(x.shape[1], memory_valid)

        def sa(y):
            return drop(self_attn(y, y, deterministic=deterministic), deterministic=deterministic)

        def ca(y):
            return drop(cross_attn(y, memory, mask=mask, deterministic=deterministic),
                        deterministic=deterministic)

        def fb(y):
            return drop(ff(y, deterministic), deterministic=deterministic)

        if c.norm_first:
            x = x + sa(n1(x))
            x = x + ca(n2(x))
            return x + fb(n3(x))
        x = n1(x + sa(x))
        x = n2(x + ca(x))
        return n3(x + fb(x))


class Encoder(nn.Module):
    """``config.layers`` encoder layers: tokens ``(B, n, d)``, key mask ``(B, n)`` or None.

    ``outputs``: only the first ``outputs`` rows of the last layer are computed and returned
    (``(B, outputs, d)``; see :class:`EncoderLayer`). ``dtype``: operand type of the matrix
    products (see :func:`dot_general_for`)."""

    config: ModelConfig
    dtype: jnp.dtype = F32

    @nn.compact
    def __call__(self, x, valid=None, *, deterministic: bool = True,
                 outputs: int | None = None):
        last = self.config.layers - 1
        for i in range(self.config.layers):
            x = EncoderLayer(self.config, self.dtype, name=f"layer{i}")(
                x, valid, deterministic, outputs if i == last else None)
        return x


class Decoder(nn.Module):
    """``config.layers`` decoder layers: target ``(B, q, d)`` over memory ``(B, m, d)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, x, memory, memory_valid=None, *, deterministic: bool = True):
        for i in range(self.config.layers):
            x = DecoderLayer(self.config, name=f"layer{i}")(x, memory, memory_valid,
                                                             deterministic)
        return x
