"""Pure training and evaluation steps of the calibrator; K seeds vmapped; data parallel.

A batch is a dict of model inputs (:func:`uavcal_jax.calib.batch.model_batch`): ``frames``
``(B, T, h, w)`` / ``(B, T, 3, h, w)`` (absent for the IMU-only model), *clean* ``imu``
``(B, T, C)``, ``mask (B, T)`` bool, optionally ``weight (B,)`` (0 on padding windows of a
last, short batch), for evaluation the injected ``offset (B, C)``, and under the ``total``
label the sensor's own ``bias (B, C)``, which the label adds to the offset. With
``ModelConfig.motion_tokens`` the batch also holds the clean full-rate motion inputs
(:data:`uavcal_jax.calib.model.MOTION_KEYS`); the steps add the offset's gyro channels to
every sample of ``gyro_seq`` as to ``imu`` (:func:`_motion`).

- :func:`train_step` ``(state, batch, key) -> (state, metrics)``: splits ``key`` into an
  offset key and a dropout key, under ``train.mounting="random"`` turns each window's IMU
  by a random mounting (:mod:`uavcal_jax.calib.mounting`), draws a new offset per window by
  the configured protocol (:func:`uavcal_jax.calib.inject.training_offsets`, from the
  training statistics held in the state), injects it, and takes one AdamW step on the eq. 18
  loss.
- :func:`eval_step` ``(state, batch) -> metrics``: injects ``batch["offset"]``, predicts in
  deterministic mode, returns the loss terms, the metric sums of
  :func:`uavcal_jax.calib.metrics.metric_sums` (add them over batches) and ``pred`` (and, for
  a model with an uncertainty, ``ModelConfig.variance``, ``log_sigma``; the loss then adds
  the Gaussian NLL term ``nll``).
- K seeds: :func:`create_train_states` builds K independently initialised states stacked on
  a leading axis (one key each) and :func:`train_step_seeds` / :func:`eval_step_seeds` step
  all of them at once with ``jax.vmap`` (one batch, K keys: own dropout and offset streams).
"""

from __future__ import annotations

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from uavcal_jax.calib.config import CalibConfig, TrainConfig
from uavcal_jax.calib.inject import (
    ImuStats,
    imu_statistics,
    inject,
    offset_moments,
    training_offsets,
)
from uavcal_jax.calib.loss import calibration_loss, gaussian_nll, tilt_loss
from uavcal_jax.calib.metrics import metric_sums
from uavcal_jax.calib.model import (
    ALIGNMENT_INPUTS,
    MOTION_KEYS,
    NORMALIZATION,
    Calibrator,
    split_prediction,
)
from uavcal_jax.calib.mounting import isotropic_statistics, random_mountings, remount

__all__ = [
    "CalibState",
    "create_train_state",
    "create_train_states",
    "eval_step",
    "eval_step_seeds",
    "make_optimizer",
    "normalization",
    "train_step",
    "train_step_seeds",
]


#: Floor of the standardisation's divisors (a channel constant over the training set).
_MIN_STD = 1e-6


def normalization(config: CalibConfig, stats: ImuStats) -> dict:
    """The model's ``"normalization"`` collection (see :mod:`uavcal_jax.calib.model`): the
    training IMU's per-channel mean and standard deviation and those of the offsets the
    injection protocol draws (:func:`uavcal_jax.calib.inject.offset_moments`), ``(C,)``
    float32 each; empty when ``config.model.standardize`` is off."""
    if not config.model.standardize:
        return {}
    offset_mean, offset_std = offset_moments(config.injection, stats)
    return {"imu_mean": jnp.asarray(stats.mean, jnp.float32),
            "imu_std": jnp.maximum(jnp.asarray(stats.std, jnp.float32), _MIN_STD),
            "offset_mean": offset_mean, "offset_std": jnp.maximum(offset_std, _MIN_STD)}


class CalibState(flax.struct.PyTreeNode):
    """Everything a training run carries: ``step ()`` int32, ``params``, ``batch_stats``
    (the RGB batch norm's running statistics; empty for gray), ``opt_state``, the training
    set's ``imu_stats`` (drive the paper protocol) and the static ``config``."""

    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    imu_stats: ImuStats
    config: CalibConfig = flax.struct.field(pytree_node=False)

    @property
    def model(self) -> Calibrator:
        return Calibrator(self.config.model)

    def variables(self) -> dict:
        """The Flax variables for ``Calibrator.apply`` (the standardisation constants come
        from ``imu_stats`` and the injection protocol: :func:`normalization`)."""
        norm = normalization(self.config, self.imu_stats)
        return {"params": self.params,
                **({"batch_stats": self.batch_stats} if self.batch_stats else {}),
                **({NORMALIZATION: norm} if norm else {})}


def _is_key_bias(path, _leaf) -> bool:
    names = [getattr(k, "key", None) for k in path]
    return len(names) >= 2 and names[-2:] == ["key", "bias"]


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """AdamW (decoupled weight decay on every parameter, as PyTorch's ``AdamW``).

    With ``config.freeze_key_bias`` the gradients of the attention *key* biases are zeroed
    first: softmax is invariant to a shift shared by every key, so their exact gradient is
    zero and what autodiff returns is rounding noise, which Adam's normalisation would turn
    into steps of size ``learning_rate`` in random directions (they then only decay).
    """
    adamw = optax.adamw(config.learning_rate, b1=config.b1, b2=config.b2, eps=config.eps,
                        weight_decay=config.weight_decay)
    if not config.freeze_key_bias:
        return adamw
    mask = functools.partial(jax.tree_util.tree_map_with_path, _is_key_bias)
    return optax.chain(optax.masked(optax.set_to_zero(), mask), adamw)


def _inputs(config: CalibConfig, batch: dict):
    return (batch.get("frames") if config.model.use_video else None, batch["imu"],
            jnp.asarray(batch["mask"], bool))


def _motion(config: CalibConfig, batch: dict, offsets: jax.Array | None) -> dict | None:
    """The model's motion inputs (``None`` without ``motion_tokens``) with the gyro channels
    of ``offsets (B, C)`` (``None``: clean) added to every gyro sample; zero-duration
    padding samples do not move the composed rotation, so they need no mask."""
    if not config.model.motion_tokens:
        return None
    if config.model.imu_channels == 3 and config.injection.single_sensor != "gyro":
        raise ValueError("model.motion_tokens reads the gyro: a 3-channel model needs "
                         "injection.single_sensor=gyro")
    motion = {k: batch[k] for k in MOTION_KEYS}
    if config.model.closed_form == "rotation_alignment":
        motion.update({k: batch[k] for k in ALIGNMENT_INPUTS})
    if offsets is not None:
        gyro = jnp.asarray(motion["gyro_seq"], jnp.float32)
        motion["gyro_seq"] = gyro + jnp.asarray(offsets, jnp.float32)[:, None, None, :3]
        if "accel_start" in motion:  # the alignment of the injected IMU (linear in it)
            motion["accel_start"] = shifted_accel_start(
                motion["accel_start"], batch["accel_response"], offsets)
    return motion


def shifted_accel_start(start, response, offsets):
    """``start (B, 3) + response (B, 3, 3) @ offsets[:, 3:]``: a window's metric accelerometer
    start as the alignment of its IMU with the constant ``offsets (B, 6)`` added
    (:mod:`uavcal_jax.data.window_alignment`)."""
    return (jnp.asarray(start, jnp.float32)
            + jnp.einsum("bij,bj->bi", jnp.asarray(response, jnp.float32),
                         jnp.asarray(offsets, jnp.float32)[:, 3:6]))


def _init(config: CalibConfig, key: jax.Array, sample: dict, stats: ImuStats) -> CalibState:
    frames, imu, mask = _inputs(config, sample)
    variables = Calibrator(config.model).init({"params": key}, frames, imu, mask,
                                              _motion(config, sample, None))
    params = variables["params"]
    return CalibState(step=jnp.zeros((), jnp.int32), params=params,
                      batch_stats=variables.get("batch_stats", {}),
                      opt_state=make_optimizer(config.train).init(params),
                      imu_stats=ImuStats(*(jnp.asarray(s, jnp.float32) for s in stats)),
                      config=config)


_init_one = jax.jit(_init, static_argnums=0)


def _first_window(batch: dict) -> dict:
    return {k: np.asarray(v)[:1] for k, v in batch.items()}


def _stats(config: CalibConfig, sample_batch: dict, imu_stats: ImuStats | None) -> ImuStats:
    """The state's training statistics: ``imu_stats`` or ``sample_batch``'s, made
    mounting-free under ``train.mounting="random"``
    (:func:`~uavcal_jax.calib.mounting.isotropic_statistics`)."""
    if imu_stats is None:
        imu_stats = imu_statistics(np.asarray(sample_batch["imu"]),
                                   np.asarray(sample_batch["mask"]))
    if config.train.mounting == "random":
        return isotropic_statistics(imu_stats)
    return imu_stats


def create_train_state(config: CalibConfig, key: jax.Array, sample_batch: dict,
                       imu_stats: ImuStats | None = None) -> CalibState:
    """A freshly initialised state. ``sample_batch`` fixes the shapes (its first window is
    used: frame size, frames per window when ``max_frames`` is None); ``imu_stats`` are the
    training set's (:func:`uavcal_jax.calib.inject.imu_statistics`), by default those of
    ``sample_batch``'s clean IMU (made mounting-free under ``train.mounting="random"``)."""
    stats = _stats(config, sample_batch, imu_stats)
    return _init_one(config, key, _first_window(sample_batch), stats)


def create_train_states(config: CalibConfig, keys: jax.Array, sample_batch: dict,
                        imu_stats: ImuStats | None = None) -> CalibState:
    """K states (``keys (K,)``, one per seed) stacked on a leading axis; state ``k`` equals
    ``create_train_state(config, keys[k], ...)``. The inits run one by one through the same
    compiled function (an init runs once per run; a vmapped one would cost its own
    compile), the steps then run vmapped."""
    stats = _stats(config, sample_batch, imu_stats)
    first = _first_window(sample_batch)
    states = [_init_one(config, k, first, stats) for k in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


def _weight(batch: dict, size: int) -> jax.Array:
    w = batch.get("weight")
    return jnp.ones(size, jnp.float32) if w is None else jnp.asarray(w, jnp.float32)


def _apply(state: CalibState, params, frames, imu, mask, *, train: bool, key=None,
           motion=None):
    """``(out, batch_stats, tilt)``: the model's output (:func:`split_prediction`), the new
    batch statistics and the tilt head's ``(B, T, 3)`` (``None`` without one)."""
    model = state.model
    variables = state.replace(params=params).variables()
    mutable = (["batch_stats"] if train and state.batch_stats else []) + (
        ["intermediates"] if state.config.model.tilt_head else [])
    kwargs = {"deterministic": False, "rngs": {"dropout": key}} if train else {}
    if not mutable:
        return model.apply(variables, frames, imu, mask, motion, **kwargs), state.batch_stats, None
    out, updates = model.apply(variables, frames, imu, mask, motion, mutable=mutable, **kwargs)
    sown = updates.get("intermediates")
    tilt = sown["noise_predictor"]["tilt"][0] if sown else None
    return out, updates.get("batch_stats", state.batch_stats), tilt


def _offset_scale(state: CalibState) -> jax.Array:
    """Per-channel scale of the standardised loss: the protocol's offset standard deviation."""
    return jnp.maximum(offset_moments(state.config.injection, state.imu_stats)[1], _MIN_STD)


def _label(batch: dict, offsets: jax.Array) -> jax.Array:
    """What the model learns to predict: the injected ``offsets (B, C)``, plus the sensor's
    own bias ``batch["bias"]`` under the ``total`` label (:func:`uavcal_jax.calib.data.gather`
    adds it only then)."""
    return offsets + batch["bias"] if "bias" in batch else offsets


def _loss(state: CalibState, pred, log_sigma, target, weight, tilt=None, batch=None):
    """Eq. 18 (:func:`~uavcal_jax.calib.loss.calibration_loss`), plus ``w_nll`` times the
    uncertainty's negative log-likelihood (term ``nll``) for a model that predicts one, plus
    ``w_tilt`` times the tilt head's loss against ``batch["up"]`` (terms ``tilt`` and
    ``tilt_deg``, :func:`~uavcal_jax.calib.loss.tilt_loss`) for a model with one."""
    config = state.config.loss
    loss, terms = calibration_loss(pred, target, config, weight, _offset_scale(state))
    if log_sigma is not None:
        nll = gaussian_nll(pred, log_sigma, target, weight)
        loss, terms = loss + config.w_nll * nll, {**terms, "nll": nll}
    if tilt is not None and "up" in batch:  # evaluated without ground truth: no tilt term
        term, angle = tilt_loss(tilt, batch["up"], batch["mask"], weight)
        loss, terms = loss + config.w_tilt * term, {**terms, "tilt": term, "tilt_deg": angle}
    return loss, terms


def _train_step(state: CalibState, batch: dict, key: jax.Array):
    config = state.config
    k_offset, k_dropout = jax.random.split(key)
    if config.train.mounting == "random":  # its own stream: the fixed mounting's draws stay
        k_mount = jax.random.fold_in(key, 1)
        batch = remount(batch, random_mountings(k_mount, batch["imu"].shape[0]))
    frames, clean, mask = _inputs(config, batch)
    weight = _weight(batch, clean.shape[0])
    offsets = training_offsets(k_offset, config.injection, state.imu_stats, clean.shape[0])
    imu = inject(clean, offsets, mask)
    motion = _motion(config, batch, offsets)
    target = _label(batch, offsets)

    def loss_fn(params):
        out, stats, tilt = _apply(state, params, frames, imu, mask, train=True, key=k_dropout,
                                  motion=motion)
        pred, log_sigma = split_prediction(out, config.model)
        loss, terms = _loss(state, pred, log_sigma, target, weight, tilt, batch)
        return loss, (terms, stats, pred)

    (loss, (terms, batch_stats, pred)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
        state.params)
    updates, opt_state = make_optimizer(config.train).update(grads, state.opt_state,
                                                             state.params)
    state = state.replace(step=state.step + 1, params=optax.apply_updates(state.params, updates),
                          batch_stats=batch_stats, opt_state=opt_state)
    err = jnp.sum(weight[:, None] * jnp.square(pred - target))
    metrics = {"loss": loss, **terms, "grad_norm": optax.tree.norm(grads),
               "offset_rmse": jnp.sqrt(err / jnp.maximum(jnp.sum(weight) * pred.shape[1], 1))}
    return state, metrics


def _eval_step(state: CalibState, batch: dict):
    config = state.config
    frames, clean, mask = _inputs(config, batch)
    weight = _weight(batch, clean.shape[0])
    offsets = jnp.asarray(batch["offset"], jnp.float32)
    out, _, tilt = _apply(state, state.params, frames, inject(clean, offsets, mask), mask,
                          train=False, motion=_motion(config, batch, offsets))
    pred, log_sigma = split_prediction(out, config.model)
    target = _label(batch, offsets)
    loss, terms = _loss(state, pred, log_sigma, target, weight, tilt, batch)
    result = {"loss": loss, **terms, "sums": metric_sums(pred, target, weight, log_sigma),
              "pred": pred}
    return result if log_sigma is None else {**result, "log_sigma": log_sigma}


@jax.jit
def train_step(state: CalibState, batch: dict, key: jax.Array):
    """``(state, batch, key) -> (state, metrics)``: one AdamW step (see the module
    docstring); ``metrics`` scalars: ``loss``, ``offset``, ``sign``, ``magnitude``,
    ``sign_exact``, ``grad_norm`` and ``offset_rmse`` (against the label: :func:`_label`)."""
    return _train_step(state, batch, key)


@jax.jit
def eval_step(state: CalibState, batch: dict):
    """``(state, batch) -> metrics``: deterministic predictions ``pred (B, C)`` with
    ``batch["offset"]`` injected into the clean IMU, the loss terms and metric ``sums``."""
    return _eval_step(state, batch)


_train_seeds = jax.vmap(_train_step, in_axes=(0, None, 0))
_eval_seeds = jax.vmap(_eval_step, in_axes=(0, None))


@jax.jit
def train_step_seeds(states: CalibState, batch: dict, keys: jax.Array):
    """``(states, batch, keys (K,)) -> (states, metrics)``: K stacked seeds on one batch,
    each with its own key; every output has a leading ``K`` axis."""
    return _train_seeds(states, batch, keys)


@jax.jit
def eval_step_seeds(states: CalibState, batch: dict):
    """``(states, batch) -> metrics`` of K stacked states (leading ``K`` axis)."""
    return _eval_seeds(states, batch)
