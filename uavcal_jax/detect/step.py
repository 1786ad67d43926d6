"""The detector's train state and its one pure jitted training step (loss, update, EMA).

:func:`make_train_step` returns ``step(state, images, targets) -> (state, metrics)`` where
``state`` is a :class:`TrainState` pytree (params, BN statistics, optimizer state, EMA of
params and BN statistics, step count). The EMA follows YOLOv5's ``ModelEMA``:
``d = decay * (1 - exp(-updates / tau))`` applied after every step to params and BN
statistics.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from uavcal_jax.detect.config import DetectorConfig, TrainConfig
from uavcal_jax.detect.model import build_detector
from uavcal_jax.detect.optim import make_optimizer


class TrainState(NamedTuple):
    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    ema_params: Any
    ema_batch_stats: Any

    def variables(self, ema: bool = True) -> dict:
        """Model variables for inference (the EMA ones by default)."""
        if ema:
            return {"params": self.ema_params, "batch_stats": self.ema_batch_stats}
        return {"params": self.params, "batch_stats": self.batch_stats}


@functools.lru_cache(maxsize=8)
def _jitted_init(det_cfg: DetectorConfig) -> Callable:
    """One compiled initialiser per configuration (compiling it is slow on CPU)."""
    h, w = det_cfg.img_size
    model = build_detector(det_cfg)

    def init(key):
        variables = model.init(key, jnp.zeros((1, h, w, 3), jnp.float32), train=False)
        return {"params": variables["params"], "batch_stats": variables["batch_stats"]}

    return jax.jit(init)


def init_variables(key: jax.Array, det_cfg: DetectorConfig) -> dict:
    """``{"params", "batch_stats"}`` as :func:`~uavcal_jax.detect.model.init_detector`, with
    the compiled initialiser cached per configuration."""
    return _jitted_init(det_cfg)(key)


def abstract_variables(det_cfg: DetectorConfig) -> dict:
    """The shapes and dtypes of :func:`init_variables` (nothing is computed)."""
    return jax.eval_shape(lambda: init_variables(jax.random.PRNGKey(0), det_cfg))


def init_train_state(key: jax.Array, det_cfg: DetectorConfig, tx) -> TrainState:
    variables = init_variables(key, det_cfg)
    params, stats = variables["params"], variables["batch_stats"]
    copy = lambda tree: jax.tree.map(jnp.copy, tree)  # noqa: E731 - own buffers (donation)
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, batch_stats=stats,
                      opt_state=tx.init(params), ema_params=copy(params),
                      ema_batch_stats=copy(stats))


@functools.lru_cache(maxsize=8)
def compiled_training(det_cfg: DetectorConfig, cfg: TrainConfig, steps_per_epoch: int):
    """``(tx, step)`` for a configuration, cached so that several runs in one process (resume,
    experiments, tests) compile the train step once."""
    tx = make_optimizer(cfg, steps_per_epoch, abstract_variables(det_cfg)["params"])
    return tx, make_train_step(det_cfg, cfg, tx)


def make_train_step(det_cfg: DetectorConfig, cfg: TrainConfig, tx) -> Callable:
    """A jitted ``step(state, images, targets) -> (state, metrics)``; ``state`` is donated."""
    from uavcal_jax.detect.loss import yolo_loss

    model = build_detector(det_cfg)

    def loss_fn(params, batch_stats, images, targets):
        outputs, updates = model.apply({"params": params, "batch_stats": batch_stats}, images,
                                       train=True, mutable=["batch_stats"])
        loss, parts = yolo_loss(outputs, targets, det_cfg)
        return loss, (updates["batch_stats"], parts)

    def step(state: TrainState, images, targets):
        (loss, (stats, parts)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, state.batch_stats, images, targets)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        n = state.step + 1
        if cfg.ema:
            d = cfg.ema_decay * (1.0 - jnp.exp(-n.astype(jnp.float32) / cfg.ema_tau))
            mix = lambda e, p: (d * e + (1.0 - d) * p).astype(p.dtype)  # noqa: E731
            ema_params = jax.tree.map(mix, state.ema_params, params)
            ema_stats = jax.tree.map(mix, state.ema_batch_stats, stats)
        else:
            ema_params, ema_stats = params, stats
        metrics = dict(parts)
        metrics["loss"] = loss
        metrics["grad_norm"] = optax.tree.norm(grads)
        return TrainState(n, params, stats, opt_state, ema_params, ema_stats), metrics

    return jax.jit(step, donate_argnums=(0,))
