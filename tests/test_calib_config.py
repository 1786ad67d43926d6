"""Calibrator config: paper defaults, key=value overrides, dict round trip, the run root and
its presets (``shipped`` is the shipped weights' configuration, read from their older layout),
the budget mode's stride, and the default model's parameter count against the PyTorch peer
(../shared/tools/peer_calibrator_torch.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib.config import CalibConfig, CalibRunConfig, LoopConfig, ModelConfig
from uavcal_jax.calib.loop import read_run_config
from uavcal_jax.calib.model import Calibrator
from uavcal_jax.calib.presets import PRESETS, budget_stride, resolve_configs
from uavcal_jax.calib.pretrained import DEFAULT_WEIGHTS
from uavcal_jax.config import UnknownConfigKey, apply_overrides, from_dict, to_dict
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


def test_run_root_sections_and_round_trip():
    run = apply_overrides(CalibRunConfig(), ["model.d_model=64", "loop.validation=loo",
                                             "window.size=160x96"])
    assert run.calib == apply_overrides(CalibConfig(), ["model.d_model=64"])
    assert run.loop == LoopConfig(validation="loo") and run.window.size == (160, 96)
    assert CalibRunConfig.of(run.calib, run.loop, run.window) == run
    assert from_dict(CalibRunConfig, to_dict(run)) == run


def test_presets_are_typed_and_shipped_is_the_shipped_weights():
    assert PRESETS["paper"] == CalibRunConfig()
    small = PRESETS["small"]
    assert (small.model.d_model, small.window.size, small.window.frame_step) == (64, (160, 96),
                                                                                2)
    # the weights' config.json predates the root (sections nested under "calib")
    assert read_run_config(DEFAULT_WEIGHTS) == PRESETS["shipped"]


def test_resolve_preset_then_arguments_then_sets():
    run = resolve_configs(["train.epochs=9", "window.duration=4"], preset="small",
                          protocol="physical", epochs=3, validation="kfold")
    assert run.train.epochs == 9 and run.injection.protocol == "physical"
    assert run.loop.validation == "kfold" and run.window.duration == 4
    assert run.model == PRESETS["small"].model
    assert resolve_configs(preset=PRESETS["shipped"], arguments={"loop.val_offsets": None,
                                                                 "train.seeds": 2}
                           ).train.seeds == 2
    with pytest.raises(UnknownConfigKey, match="'loop.nope'"):
        resolve_configs(["loop.nope=1"])
    with pytest.raises(ValueError, match="unknown preset"):
        resolve_configs(preset="tiny")


def test_budget_stride_is_the_modes_window_length():
    mode = resolve_configs(preset="small")
    run = budget_stride(resolve_configs(["window.duration=4"], preset="small"), mode,
                        ["window.duration=4"])
    assert run.window.duration == 4 and run.window.stride == mode.window.duration == 10
    kept = resolve_configs(["window.stride=2"], preset="small")
    assert budget_stride(kept, mode, ["window.stride=2"]) == kept


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
