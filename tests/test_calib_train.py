"""Training steps: the loss falls on a fixed batch, and K vmapped seeds equal K single runs."""

import jax
import numpy as np
import pytest

from uavcal_jax.calib.config import CalibConfig
from uavcal_jax.calib.train import (
    create_train_state,
    create_train_states,
    eval_step,
    train_step,
    train_step_seeds,
)
from uavcal_jax.config import apply_overrides

# tiny model, 64x36 frames, patch 16, windows of 8 frames, batch 4 (one padded frame)
CONFIG = apply_overrides(CalibConfig(), [
    "model.d_model=32", "model.layers=1", "model.heads=2", "model.patch=16,16",
    "train.batch_size=4", "train.learning_rate=1e-3"])
_rng = np.random.default_rng(0)
BATCH = {"frames": _rng.integers(0, 256, (4, 8, 36, 64), dtype=np.uint8),
         "imu": _rng.normal(0, 1, (4, 8, 6)).astype(np.float32),
         "mask": np.ones((4, 8), bool)}
BATCH["mask"][1, -1] = False
BATCH["imu"][1, -1] = 0
STEPS = 3


def step_keys(i, k=None):
    key = jax.random.fold_in(jax.random.key(1), i)
    return key if k is None else jax.random.split(key, k)


def _run(state, n=STEPS):
    losses = []
    for i in range(n):
        state, m = train_step(state, BATCH, step_keys(i))
        losses.append(float(m["loss"]))
    return state, losses


@pytest.fixture(scope="module")
def single(xla_cache):
    """Seed-0 state and its parameters after ``STEPS`` steps (one device)."""
    state = create_train_state(CONFIG, jax.random.key(0), BATCH)
    return state, _run(state)


def _max_diff(a, b):
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_steps_on_a_fixed_batch_lower_the_loss(single):
    state, _ = single
    key = jax.random.key(7)  # one key: the same offsets and dropout every step
    losses = []
    # the standardised head starts at zero (the mean offset); a few steps grow it
    for _ in range(25):
        state, m = train_step(state, BATCH, key)
        losses.append(float(m["loss"]))
    assert np.all(np.isfinite(losses)) and losses[-1] < 0.8 * losses[0], losses
    assert int(state.step) == 25
    offsets = np.full((4, 6), 0.5, np.float32)
    out = eval_step(state, {**BATCH, "offset": offsets})
    assert out["pred"].shape == (4, 6) and float(out["sums"]["count"].sum()) == 24


def test_vmapped_seeds_equal_single_seed_runs(single):
    k = 3
    init_keys = jax.random.split(jax.random.key(0), k)
    states = create_train_states(CONFIG, init_keys, BATCH)
    for i in range(STEPS):
        states, metrics = train_step_seeds(states, BATCH, step_keys(i, k))
    assert metrics["loss"].shape == (k,)
    seeds = [jax.tree.map(lambda x, j=j: x[j], states.params) for j in range(k)]
    assert min(_max_diff(seeds[a], seeds[b]) for a in range(k) for b in range(a)) > 1e-2
    for j in (0, k - 1):  # first and last seed against their own single-seed runs
        alone = create_train_state(CONFIG, init_keys[j], BATCH)
        for i in range(STEPS):
            alone, _ = train_step(alone, BATCH, step_keys(i, k)[j])
        assert _max_diff(seeds[j], alone.params) < 1e-5


def test_total_label_adds_the_sensor_bias_to_the_offset(single):
    """Under the ``total`` label the batch's ``bias`` joins the injected offset in the target:
    a bias equal to the prediction minus the offset makes the offset error vanish."""
    state, _ = single
    offset = np.tile(np.float32([0.02, -0.01, 0.03, 0.1, -0.2, 0.05]), (4, 1))
    injected = eval_step(state, {**BATCH, "offset": offset})
    bias = np.asarray(injected["pred"]) - offset
    total = eval_step(state, {**BATCH, "offset": offset, "bias": bias})
    np.testing.assert_array_equal(np.asarray(total["pred"]), np.asarray(injected["pred"]))
    assert float(injected["offset"]) > 1e-3 and float(total["offset"]) < 1e-9



@pytest.mark.heavy  # CI budget: 50 s; the CLI run with an uncertainty stays
def test_uncertainty_head_leaves_the_estimate_alone(single):
    """``model.variance``: the offsets' parameters after ``STEPS`` steps are those of the model
    without it, to rounding (the NLL's gradient is stopped before the decoder, Adam is per
    parameter), the uncertainty head moves, and evaluation scores the z-scores' spread."""
    from uavcal_jax.calib.metrics import metrics_from_sums
    from uavcal_jax.calib.model import split_prediction
    from uavcal_jax.config import apply_overrides

    init, (plain, _) = single
    config = apply_overrides(CONFIG, ["model.variance=true"])
    state = create_train_state(config, jax.random.key(0), BATCH)

    def without_sigma(params):
        head = dict(params["noise_predictor"])
        sigma = head.pop("sigma_head")
        return {**params, "noise_predictor": head}, sigma

    start, sigma0 = without_sigma(state.params)
    assert _max_diff(start, init.params) == 0  # adding the head changes no other draw
    for i in range(STEPS):
        state, m = train_step(state, BATCH, step_keys(i))
    assert np.isfinite(float(m["nll"]))
    trained, sigma = without_sigma(state.params)
    assert _max_diff(trained, plain.params) < 1e-7  # the same, to XLA's rounding
    assert _max_diff(sigma, sigma0) > 1e-4

    offsets = np.tile(np.float32([0.02, -0.01, 0.03, 0.1, -0.2, 0.05]), (4, 1))
    out = eval_step(state, {**BATCH, "offset": offsets})
    full = state.model.apply(state.variables(), BATCH["frames"], BATCH["imu"] + offsets[:, None]
                             * BATCH["mask"][..., None], BATCH["mask"])
    pred, log_sigma = split_prediction(np.asarray(full), config.model)
    np.testing.assert_allclose(pred, out["pred"], atol=1e-5)
    np.testing.assert_allclose(log_sigma, out["log_sigma"], atol=1e-5)
    z = (pred - offsets) / np.exp(log_sigma)
    scores = metrics_from_sums(out["sums"])
    np.testing.assert_allclose(scores["z_rms_per_channel"], np.sqrt(np.mean(z ** 2, 0)),
                               rtol=1e-4)
    np.testing.assert_allclose(scores["sigma_rms"], np.sqrt(np.mean(np.exp(2 * log_sigma))),
                               rtol=1e-4)
