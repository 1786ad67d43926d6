"""The calibrator network: patch unfolding, frame-token reuse equals the full model, padded
frames are ignored, the IMU-only variant, and the RGB colour-compression path (eq. 1-2)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib import inference
from uavcal_jax.calib.config import CalibConfig
from uavcal_jax.calib.model import (
    GRAY_WEIGHTS,
    NORMALIZATION,
    Calibrator,
    patchify,
    without_correction,
)
from uavcal_jax.calib.train import create_train_state, train_step
from uavcal_jax.config import apply_overrides

# The tiny configuration of tests/test_calib_train.py: its initialiser compiles once for both.
CONFIG = apply_overrides(CalibConfig(), [
    "model.d_model=32", "model.layers=1", "model.heads=2", "model.patch=16,16",
    "train.batch_size=4", "train.learning_rate=1e-3"])
TINY = CONFIG.model
H, W, T = 36, 64, 8  # 36 rows pad to 48: 3 x 4 = 12 patches of 16x16


@pytest.fixture(scope="module")
def sequence():
    """12 frames of a sequence, and 4 windows of 8 into it (stride 2; the last one has a
    padded slot)."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (12, H, W), dtype=np.uint8)
    index = np.stack([np.arange(s, s + T) for s in (0, 2, 4, 4)]).astype(np.int32)
    index[3, 5] = -1
    mask = index >= 0
    imu = rng.normal(0, 1, (4, T, 6)).astype(np.float32) * mask[..., None]
    return frames, index, mask, imu


@pytest.fixture(scope="module")
def gray(sequence, xla_cache):
    """The tiny gray model, its variables and its jitted apply (float32 frames: one compile
    serves every test)."""
    frames, index, mask, imu = sequence
    model = Calibrator(TINY)
    state = create_train_state(CONFIG, jax.random.key(0),
                               {"frames": frames[index[:1]], "imu": imu[:1], "mask": mask[:1]})
    # the standardised head starts at zero (every window gets the mean offset): give it
    # weights, so that outputs depend on the inputs as a trained model's do
    variables = state.variables()
    head = variables["params"]["noise_predictor"]["head"]
    head["kernel"] = 0.3 * jax.random.normal(jax.random.key(5), head["kernel"].shape)
    return model, variables, jax.jit(model.apply)


def _gather(frames, index):
    out = frames[np.maximum(index, 0)].astype(np.float32)
    out[index < 0] = 0
    return out


def test_patchify_matches_a_direct_unfold():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 5, 7)).astype(np.float32)
    got = np.asarray(patchify(jnp.asarray(x), (2, 3)))
    padded = np.zeros((2, 6, 9), np.float32)
    padded[:, :5, :7] = x
    want = [[padded[i, r:r + 2, c:c + 3].ravel() for r in range(0, 6, 2) for c in range(0, 9, 3)]
            for i in range(2)]
    np.testing.assert_array_equal(got, np.asarray(want))


def test_reusing_frame_tokens_equals_the_full_model(gray, sequence):
    model, variables, apply = gray
    frames, index, mask, imu = sequence
    full = apply(variables, _gather(frames, index), imu, mask)
    assert full.shape == (4, 6) and full.dtype == jnp.float32
    tokens = inference.encode_frames(model, variables, frames, chunk=5)  # 3 chunks, last padded
    assert tokens.shape == (12, TINY.d_model)
    reused = inference.predict_windows(model, variables, tokens, index, mask, imu)
    np.testing.assert_allclose(np.asarray(reused), np.asarray(full), atol=1e-5, rtol=1e-5)
    # windows 2 and 3 differ only by a padded slot: it must change the prediction
    assert np.abs(np.asarray(full[2] - full[3])).max() > 1e-4


def test_standardization_is_an_affine_wrap_of_the_raw_network(gray, sequence):
    """With ``standardize`` the network reads ``(imu - imu_mean) / imu_std`` and its head's
    output ``y`` becomes ``offset_mean + offset_std * y``: the raw model with the same
    weights, fed standardised IMU, must give ``y``."""
    model, variables, apply = gray
    frames, index, mask, imu = sequence
    norm = {"imu_mean": jnp.asarray([0.1, -0.2, 0.3, 9.8, 0.1, -0.4]),
            "imu_std": jnp.asarray([0.5, 0.4, 0.3, 1.5, 1.0, 2.0]),
            "offset_mean": jnp.asarray([0.0, 1.0, 2.0, 3.0, 4.0, 5.0]),
            "offset_std": jnp.asarray([1.0, 2.0, 0.5, 0.25, 3.0, 1.5])}
    x = _gather(frames, index)
    got = apply({**variables, NORMALIZATION: norm}, x, imu, mask)
    raw = Calibrator(dataclasses.replace(TINY, standardize=False))
    z = (imu - np.asarray(norm["imu_mean"])) / np.asarray(norm["imu_std"])
    y = raw.apply({"params": variables["params"]}, x, z, mask)
    np.testing.assert_allclose(np.asarray(got),
                               np.asarray(norm["offset_mean"] + norm["offset_std"] * y),
                               rtol=1e-5, atol=1e-5)


def test_an_untrained_standardized_model_predicts_the_mean_offset(sequence):
    frames, index, mask, imu = sequence
    state = create_train_state(CONFIG, jax.random.key(3),
                               {"frames": frames[index[:1]], "imu": imu[:1], "mask": mask[:1]})
    out = Calibrator(TINY).apply(state.variables(), _gather(frames, index), imu, mask)
    want = state.variables()[NORMALIZATION]["offset_mean"]
    np.testing.assert_array_equal(np.asarray(out), np.broadcast_to(want, out.shape))


def test_an_untrained_window_mean_head_predicts_the_window_mean(sequence):
    """``closed_form=window_mean``: the zero-initialised correction leaves each window's mean
    real IMU sample minus the training mean (padded slots left out)."""
    frames, index, mask, imu = sequence
    config = apply_overrides(CONFIG, ["model.closed_form=window_mean"])
    state = create_train_state(config, jax.random.key(3),
                               {"frames": frames[index[:1]], "imu": imu[:1], "mask": mask[:1]})
    out = Calibrator(config.model).apply(state.variables(), _gather(frames, index), imu, mask)
    means = np.stack([imu[b][mask[b]].mean(axis=0) for b in range(len(imu))])
    want = means - np.asarray(state.variables()[NORMALIZATION]["imu_mean"])
    np.testing.assert_allclose(np.asarray(out), want, atol=1e-5)
    with pytest.raises(ValueError, match="standardize"):
        apply_overrides(CONFIG, ["model.closed_form=window_mean", "model.standardize=false"])


def test_without_correction_a_trained_window_mean_head_is_its_closed_form(sequence):
    """The credit-assignment rows' "closed form alone": a head given weights (as training
    does) moves the prediction off the window mean; :func:`without_correction` puts it back
    exactly, on a state with a leading seed axis too."""
    frames, index, mask, imu = sequence
    config = apply_overrides(CONFIG, ["model.closed_form=window_mean"])
    state = create_train_state(config, jax.random.key(3),
                               {"frames": frames[index[:1]], "imu": imu[:1], "mask": mask[:1]})
    variables = state.variables()
    params = jax.tree.map(lambda x: x, variables["params"])
    head = params["noise_predictor"]["head"]
    head["kernel"] = 0.3 * jax.random.normal(jax.random.key(5), head["kernel"].shape)
    head["bias"] = jnp.ones_like(head["bias"])
    model, x = Calibrator(config.model), _gather(frames, index)
    closed = model.apply(variables, x, imu, mask)
    trained = model.apply({**variables, "params": params}, x, imu, mask)
    assert float(jnp.max(jnp.abs(trained - closed))) > 0.01
    zeroed = model.apply({**variables, "params": without_correction(params)}, x, imu, mask)
    np.testing.assert_array_equal(np.asarray(zeroed), np.asarray(closed))
    stacked = jax.tree.map(lambda a: jnp.stack([a, a]), params)
    assert all(float(jnp.max(jnp.abs(v))) == 0.0 for v in jax.tree.leaves(
        without_correction(stacked)["noise_predictor"]["head"]))


def test_padded_frames_change_nothing(gray, sequence):
    _, variables, apply = gray
    frames, index, mask, imu = sequence
    x = _gather(frames, index)
    noisy_x, noisy_imu = x.copy(), imu.copy()
    noisy_x[3, 5] = 255
    noisy_imu[3, 5] = 100.0
    np.testing.assert_allclose(np.asarray(apply(variables, noisy_x, noisy_imu, mask)),
                               np.asarray(apply(variables, x, imu, mask)), atol=1e-6)


def test_imu_only_variant_has_no_video_block(gray, sequence):
    _, gvars, _ = gray
    _, index, mask, imu = sequence
    model = Calibrator(dataclasses.replace(TINY, use_video=False))
    shapes = jax.eval_shape(lambda: model.init(jax.random.key(0), None, imu, mask))
    assert set(shapes["params"]) == {"imu_reducer", "noise_predictor"}
    # the same blocks as the video model's: reuse its trained-from-init weights
    variables = {"params": {k: gvars["params"][k] for k in shapes["params"]},
                 NORMALIZATION: gvars[NORMALIZATION]}
    out = jax.jit(lambda v, i, m: model.apply(v, None, i, m))(variables, imu, mask)
    assert out.shape == (4, 6) and bool(jnp.all(jnp.isfinite(out)))
    with pytest.raises(ValueError, match="IMU-only"):
        model.apply(variables, np.zeros((1, T, H, W)), method=Calibrator.encode_frames)


def test_rgb_path_is_gray_plus_colour_compression(gray, sequence):
    """Eq. 1-2: with the batch norm's scale and shift zeroed the CNN adds nothing, so the RGB
    model equals the gray model on the frames' luma; in training mode the batch norm's
    statistics come from the real frames only."""
    _, gvars, gapply = gray
    _, index, mask, imu = sequence
    rgb = np.random.default_rng(2).integers(0, 256, (4, T, 3, H, W)).astype(np.float32)
    model = Calibrator(dataclasses.replace(TINY, rgb=True))
    shapes = jax.eval_shape(lambda: model.init(jax.random.key(0), rgb[:1], imu[:1], mask[:1]))
    ccn_shapes = shapes["params"]["frame_encoder"]["ccn"]
    assert ccn_shapes["conv"]["kernel"].shape == (3, 3, 3, 1)
    assert set(shapes["batch_stats"]["frame_encoder"]["ccn"]["norm"]) == {"mean", "var"}
    params = dict(gvars["params"])
    params["frame_encoder"] = {**params["frame_encoder"], "ccn": {
        "conv": {"kernel": jnp.full((3, 3, 3, 1), 0.01), "bias": jnp.zeros(1)},
        "norm": {"scale": jnp.zeros(1), "bias": jnp.zeros(1)}}}
    stats = {"frame_encoder": {"ccn": {"norm": {"mean": jnp.zeros(1), "var": jnp.ones(1)}}}}

    @jax.jit
    def both(v, x, i, m, key):
        out = model.apply(v, x, i, m)
        _, upd = model.apply(v, x, i, m, deterministic=False, mutable=["batch_stats"],
                             rngs={"dropout": key})
        return out, upd["batch_stats"]["frame_encoder"]["ccn"]["norm"]

    got, new = both({"params": params, "batch_stats": stats, NORMALIZATION: gvars[NORMALIZATION]},
                    rgb, imu, mask, jax.random.key(3))
    luma = np.tensordot(np.asarray(GRAY_WEIGHTS, np.float32), rgb, axes=([0], [2]))
    want = gapply(gvars, luma, imu, mask)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-5, rtol=1e-5)
    # running mean after one step: 0.9 * 0 + 0.1 * mean of relu(conv) over real frames
    x = np.moveaxis(rgb[mask] / 255.0, 1, -1)
    conv = jax.lax.conv_general_dilated(x, np.full((3, 3, 3, 1), 0.01, np.float32), (1, 1),
                                        "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    np.testing.assert_allclose(float(new["mean"][0]), 0.1 * float(jnp.mean(jax.nn.relu(conv))),
                               rtol=1e-4)


@pytest.mark.heavy  # 70 s on CI; bfloat16 is off by default
def test_bfloat16_frame_encoder_rounds_only_its_products(gray, sequence):
    """``frame_encoder_dtype="bfloat16"``: the same parameters (a float32 checkpoint loads),
    frame tokens within bfloat16 rounding of the float32 ones but not equal to them (the
    option acts), predictions close to float32's, and a training step whose gradients match
    float32's to that rounding."""
    model, variables, apply = gray
    frames, index, mask, imu = sequence
    config = dataclasses.replace(CONFIG, model=dataclasses.replace(
        TINY, frame_encoder_dtype="bfloat16"))
    half = Calibrator(config.model)
    sample = {"frames": frames[index[:1]], "imu": imu[:1], "mask": mask[:1]}
    assert (jax.tree.structure(half.init(jax.random.key(0), *sample.values()))
            == jax.tree.structure(model.init(jax.random.key(0), *sample.values())))

    full_tokens = np.asarray(model.apply(variables, frames, method=Calibrator.encode_frames))
    half_tokens = half.apply(variables, frames, method=Calibrator.encode_frames)
    assert half_tokens.dtype == jnp.float32
    err = np.sqrt(np.mean((np.asarray(half_tokens) - full_tokens) ** 2) / np.mean(full_tokens ** 2))
    assert 1e-4 < err < 2e-2  # bfloat16 keeps 8 significant bits: relative steps of 2^-9

    want = np.asarray(apply(variables, _gather(frames, index), imu, mask))
    got = np.asarray(half.apply(variables, frames[np.maximum(index, 0)], imu, mask))
    assert np.abs(got - want).max() < 0.02 * np.abs(want - want.mean(0)).max()

    batch = {"frames": frames[np.maximum(index, 0)], "imu": imu, "mask": mask,
             "weight": np.ones(4, np.float32)}
    # (the zero-initialised head gives both the mean offset's loss: compare the gradients)
    norms = [float(train_step(create_train_state(cfg, jax.random.key(0), sample), batch,
                              jax.random.key(1))[1]["grad_norm"]) for cfg in (CONFIG, config)]
    assert norms[1] == pytest.approx(norms[0], rel=1e-3)
