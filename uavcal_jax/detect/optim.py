"""The detector's optimiser: RMSprop (the paper) or YOLOv5's SGD, warm-up and decay schedules.

Optimisers (``TrainConfig.optimizer``):

- ``"rmsprop"`` -- the paper (RPEOD section 6.2): RMSprop, learning rate 0.01, momentum 0.9,
  weight decay 1e-5, batch 8. The paper gives no decay rate or epsilon; we use the
  TensorFlow/EfficientNet convention (``rho = 0.9``, ``eps = 1e-3`` inside the square root,
  optax's ``rmsprop``). The learning rate follows ``lr_schedule`` after a linear warmup.
- ``"sgd"`` -- YOLOv5 v7.0 ``hyp.scratch-low``: SGD with Nesterov momentum 0.937, lr0 0.01,
  weight decay 5e-4 on conv/dense kernels only, a warmup of ``max(3 epochs, 100 steps)``
  (capped at half the run) during which the bias learning rate falls from 0.1 and the others
  rise from 0 while momentum rises from 0.8, then a linear (or cosine) decay to ``lrf * lr0``
  stepped per epoch.

Weight decay is L2 added to the gradient (PyTorch's ``weight_decay``), on kernels (arrays of
rank >= 2) only. Gradients are clipped to a global norm of 10 (v7.0). YOLOv5's gradient
accumulation to a nominal batch of 64 is not reproduced (every batch is a step).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optax

from uavcal_jax.detect.config import TrainConfig


def warmup_steps(cfg: TrainConfig, steps_per_epoch: int) -> int:
    """YOLOv5's ``max(round(warmup_epochs * nb), 100)``, capped at half the run."""
    if cfg.warmup_epochs <= 0:
        return 0
    n = max(round(cfg.warmup_epochs * steps_per_epoch), cfg.warmup_min_steps)
    return int(min(n, cfg.epochs * steps_per_epoch // 2))


def lr_factor(cfg: TrainConfig, epoch):
    """The per-epoch learning-rate factor ``lf(epoch)`` (YOLOv5's ``lf``)."""
    e = jnp.asarray(epoch, jnp.float32)
    if cfg.lr_schedule == "linear":
        return (1 - e / cfg.epochs) * (1.0 - cfg.lrf) + cfg.lrf
    if cfg.lr_schedule == "cosine":
        return ((1 - jnp.cos(e * math.pi / cfg.epochs)) / 2) * (cfg.lrf - 1) + 1
    return jnp.ones_like(e)


def make_schedules(cfg: TrainConfig, steps_per_epoch: int):
    """``(lr_other(step), lr_bias(step), momentum(step))`` as jnp functions of the step."""
    nw = warmup_steps(cfg, steps_per_epoch)
    bias_start = cfg.warmup_bias_lr if cfg.optimizer == "sgd" else 0.0
    mom_start = cfg.warmup_momentum if cfg.optimizer == "sgd" else cfg.momentum

    def lr_at(step, start):
        step = jnp.asarray(step, jnp.float32)
        target = cfg.lr * lr_factor(cfg, jnp.floor(step / steps_per_epoch))
        if nw == 0:
            return target
        frac = jnp.clip(step / nw, 0.0, 1.0)
        return jnp.where(step < nw, start + (target - start) * frac, target)

    def momentum(step):
        if nw == 0:
            return jnp.asarray(cfg.momentum, jnp.float32)
        frac = jnp.clip(jnp.asarray(step, jnp.float32) / nw, 0.0, 1.0)
        return mom_start + (cfg.momentum - mom_start) * frac

    return (lambda s: lr_at(s, 0.0)), (lambda s: lr_at(s, bias_start)), momentum


def current_lr(cfg: TrainConfig, steps_per_epoch: int, step: int) -> float:
    """The learning rate of the non-bias parameters at ``step``."""
    return float(make_schedules(cfg, steps_per_epoch)[0](step))


def _leaf_name(path) -> str:
    last = path[-1]
    return str(getattr(last, "key", getattr(last, "name", last)))


def param_labels(params):
    """``"bias"`` for biases (their own warmup), ``"other"`` for the rest."""
    return jax.tree_util.tree_map_with_path(
        lambda p, x: "bias" if _leaf_name(p) == "bias" else "other", params)


def decay_mask(params):
    """Weight decay on kernels (rank >= 2) only, as YOLOv5's parameter groups."""
    return jax.tree.map(lambda x: x.ndim >= 2, params)


def make_optimizer(cfg: TrainConfig, steps_per_epoch: int, params) -> optax.GradientTransformation:
    """Clip, weight decay, then RMSprop or SGD with the bias/other learning-rate schedules."""
    lr_other, lr_bias, momentum = make_schedules(cfg, steps_per_epoch)

    def core(lr):
        if cfg.optimizer == "sgd":
            return optax.inject_hyperparams(optax.sgd)(
                learning_rate=lr, momentum=momentum, nesterov=cfg.nesterov)
        return optax.inject_hyperparams(optax.rmsprop)(
            learning_rate=lr, decay=cfg.rmsprop_decay, eps=cfg.rmsprop_eps,
            momentum=cfg.momentum)

    chain = []
    if cfg.grad_clip and cfg.grad_clip > 0:
        chain.append(optax.clip_by_global_norm(cfg.grad_clip))
    if cfg.weight_decay:
        chain.append(optax.add_decayed_weights(cfg.weight_decay, mask=decay_mask(params)))
    chain.append(optax.multi_transform({"other": core(lr_other), "bias": core(lr_bias)},
                                       param_labels(params)))
    return optax.chain(*chain)
