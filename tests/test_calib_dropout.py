"""The calibrator's hash dropout: Bernoulli(1 - rate) masks, independent across keys and
elements, inverted scaling, vmappable; the frame encoder's last layer computing only the row
it returns gives the full layer's row."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib.config import ModelConfig
from uavcal_jax.calib.dropout import Dropout, attention, dropout, hash_bits, keep_mask
from uavcal_jax.calib.layers import Encoder

N = 2_000_000


@pytest.mark.parametrize("rate", [0.01, 0.1, 0.5])
def test_keep_rate_is_one_minus_rate(rate):
    kept = np.asarray(keep_mask(jax.random.key(7), (N,), rate))
    sigma = np.sqrt(rate * (1 - rate) / N)
    assert abs((1 - kept.mean()) - rate) < 5 * sigma


def test_masks_are_independent_across_keys_and_neighbours():
    rate = 0.5
    a = np.asarray(keep_mask(jax.random.key(0), (N,), rate), np.float64)
    b = np.asarray(keep_mask(jax.random.key(1), (N,), rate), np.float64)
    bound = 5 / np.sqrt(N)  # correlation of independent masks: N(0, 1/N)
    assert abs(np.corrcoef(a, b)[0, 1]) < bound
    for lag in (1, 2, 3, 1024):  # neighbouring elements, rows of a (..., 1024) tensor
        assert abs(np.corrcoef(a[:-lag], a[lag:])[0, 1]) < bound
    # every output bit is fair: a hash with weak bits would show here
    words = np.asarray(hash_bits(jax.random.key(3), (N,)))
    ones = np.unpackbits(words.view(np.uint8)).reshape(N, 32).mean(axis=0)
    assert np.all(np.abs(ones - 0.5) < 5 * 0.5 / np.sqrt(N))


def test_inverted_scaling_keeps_the_mean_and_vmaps_over_keys():
    x = jnp.ones((N,), jnp.float32)
    y = np.asarray(dropout(x, 0.2, jax.random.key(4)))
    assert set(np.unique(y)) <= {0.0, np.float32(1 / 0.8)}
    assert abs(y.mean() - 1.0) < 5 * np.sqrt(0.2 / 0.8 / N)
    keys = jax.random.split(jax.random.key(5), 3)
    ys = np.asarray(jax.vmap(lambda k: dropout(x[:1000], 0.5, k))(keys))
    np.testing.assert_array_equal(ys[0], np.asarray(dropout(x[:1000], 0.5, keys[0])))
    assert not np.array_equal(ys[0], ys[1])


def test_module_is_identity_when_deterministic_and_attention_equals_flax():
    x = jax.random.normal(jax.random.key(6), (4, 8))
    assert jnp.array_equal(Dropout(0.5).apply({}, x, deterministic=True), x)
    q, k, v = (jax.random.normal(kk, (2, 5, 3, 4)) for kk in jax.random.split(jax.random.key(8), 3))
    mask = jnp.ones((2, 1, 5, 5), bool).at[:, :, :, -1].set(False)
    np.testing.assert_allclose(attention(q, k, v, mask=mask),
                               nn.dot_product_attention(q, k, v, mask=mask), atol=1e-6)


@pytest.mark.parametrize("norm_first", [False, True])
def test_encoder_first_row_only_equals_the_full_encoder(norm_first):
    config = ModelConfig(d_model=32, heads=4, layers=2, norm_first=norm_first)
    x = jax.random.normal(jax.random.key(9), (3, 7, 32))
    valid = jnp.ones((3, 7), bool).at[1, 5:].set(False)
    enc = Encoder(config)
    params = enc.init(jax.random.key(10), x, valid)
    full = enc.apply(params, x, valid)
    first = enc.apply(params, x, valid, outputs=1)
    assert first.shape == (3, 1, 32)
    np.testing.assert_allclose(first[:, 0], full[:, 0], atol=1e-5)
