"""Calibrator config: paper defaults, key=value overrides, dict round trip, and the default
model's parameter count against the PyTorch peer (../shared/tools/peer_calibrator_torch.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib.config import CalibConfig, ModelConfig
from uavcal_jax.calib.model import Calibrator
from uavcal_jax.config import apply_overrides, from_dict, to_dict
from uavcal_jax.data.windows import WindowConfig

PEER_PARAMS = 9_700_614  # peer_calibrator_torch.py --bench: d 256, 200 frames of 320x180


def test_defaults_are_the_papers():
    c = CalibConfig()
    assert (c.model.d_model, c.model.heads, c.model.layers, c.model.ff_width) == (256, 8, 2, 1024)
    assert c.model.activation == "relu" and c.model.dropout == 0.01
    assert c.model.patch == (64, 64) and c.model.imu_channels == 6 and c.model.use_video
    assert (c.train.batch_size, c.train.learning_rate, c.train.patience) == (16, 1e-5, 3)
    assert c.injection.protocol == "paper" and c.injection.noise_multiplier == 2.0
    assert c.loss.sign_term == "sign"


def test_overrides_parse_to_field_types():
    c = apply_overrides(CalibConfig(), ["model.d_model=128", "model.patch=32x48",
                                       "model.use_video=false", "model.ff_dim=none",
                                       "loss.tau=0.2", "injection.protocol=physical",
                                       "train.seeds=4"])
    assert c.model.d_model == 128 and c.model.patch == (32, 48) and not c.model.use_video
    assert c.model.ff_dim is None and c.loss.tau == 0.2 and c.train.seeds == 4
    assert c.injection.protocol == "physical"
    assert apply_overrides(c, {"model.ff_dim": 64}).model.ff_width == 64
    assert CalibConfig().model.d_model == 256  # the original is untouched


def test_unknown_key_names_it_and_lists_valid_keys():
    with pytest.raises(KeyError) as err:
        apply_overrides(CalibConfig(), ["model.width=3"])
    msg = str(err.value)
    assert "'model.width'" in msg and "model.d_model" in msg and "train.learning_rate" in msg


@pytest.mark.parametrize("override", ["model.d_model=abc", "model.use_video=maybe",
                                      "model.heads=3", "injection.protocol=bogus", "nokey"])
def test_bad_values_raise(override):
    with pytest.raises(ValueError):
        apply_overrides(CalibConfig(), [override])


def test_dict_round_trip():
    c = apply_overrides(CalibConfig(), ["model.patch=16,16", "loss.sign_term=tanh"])
    d = to_dict(c)
    assert d["model"]["patch"] == (16, 16)
    assert from_dict(CalibConfig, d) == c
    with pytest.raises(KeyError, match="model.nope"):
        from_dict(CalibConfig, {"model": {"nope": 1}})


def _param_count(model_config: ModelConfig) -> int:
    w, h = WindowConfig().size
    n = 200  # 10 s windows of a 20 Hz camera, the peer's benchmark window
    frames = jnp.zeros((1, n, h, w), jnp.uint8)
    shapes = jax.eval_shape(lambda: Calibrator(model_config).init(
        jax.random.key(0), frames, jnp.zeros((1, n, 6)), jnp.ones((1, n), bool)))
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(shapes["params"]))


def test_parameter_count_matches_the_pytorch_peer():
    peer_like = dataclasses.replace(ModelConfig(), frame_token="first_patch")
    assert _param_count(peer_like) == PEER_PARAMS
    # the learned frame token of eq. 6 adds the token and its positional row
    assert _param_count(ModelConfig()) == PEER_PARAMS + 2 * 256
