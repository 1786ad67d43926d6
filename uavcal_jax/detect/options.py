"""The command-line options of a detector training run (``uavcal detect train`` and
``experiments/detect_aerial.py``): each an alias of ``--set KEY=VALUE`` on a
:class:`~uavcal_jax.detect.config.DetectConfig` (:class:`~uavcal_jax.argtypes.ConfigFlag`),
so their defaults and meanings are the config's.

``--optimizer`` is not a field but a recipe: it picks :meth:`TrainConfig.paper` or
:meth:`TrainConfig.yolov5` as the base that the options then change.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from typing import Any

from uavcal_jax.argtypes import (
    ConfigFlag,
    add_config_flags,
    flag_overrides,
    fraction,
    parse_imgsz,
    positive_int,
)
from uavcal_jax.config import apply_overrides
from uavcal_jax.detect.config import (
    MODELS,
    OPTIMIZERS,
    SCHEDULES,
    SELECT_METRICS,
    DetectConfig,
    TrainConfig,
)

__all__ = ["TRAIN_FLAGS", "add_train_options", "optimizer_help", "train_options"]

_paper, _sgd = TrainConfig.paper(), TrainConfig.yolov5()

#: The training options (``--mosaic`` before ``--no-augment``: with both, no augmentation).
TRAIN_FLAGS: tuple[ConfigFlag, ...] = (
    ConfigFlag("detector.model", choices=MODELS),
    ConfigFlag("train.epochs", type=positive_int, help="training epochs"),
    ConfigFlag("detector.img_size", flag="--imgsz", type=parse_imgsz, metavar="S|WxH",
               note="Letterboxed; S for square, WxH otherwise.",
               default_text="{1}x{0}, the paper's".format(*DetectConfig().detector.img_size)),
    ConfigFlag("train.batch_size", flag="--batch", type=positive_int, help="batch size"),
    ConfigFlag("train.lr", type=float, help="initial learning rate",
               default_text=f"{_paper.lr:g} for rmsprop, {_sgd.lr:g} for sgd"),
    ConfigFlag("train.lr_schedule", flag="--schedule", choices=SCHEDULES,
               help=f"learning-rate decay to lrf={_paper.lrf:g}",
               default_text=f"{_paper.lr_schedule} for rmsprop, {_sgd.lr_schedule} for sgd"),
    ConfigFlag("train.warmup_epochs", type=float,
               help=f"linear warmup (at least {_paper.warmup_min_steps} steps, at most half "
                    "the run)"),
    ConfigFlag("train.augment.mosaic", type=fraction),
    ConfigFlag("train.augment", flag="--no-augment", const=None,
               help="no augmentation (letterbox only)"),
    ConfigFlag("train.ema", help="evaluate/keep the EMA of the weights"),
    ConfigFlag("train.autoanchor",
               help="YOLOv5's check of the anchors against the training labels (k-means "
                    "anchors when the best possible recall < 0.98)"),
    ConfigFlag("train.val_fraction", type=fraction,
               help="fraction of images held out for validation"),
    ConfigFlag("train.split_seed", type=int, help="seed of the train/val split"),
    ConfigFlag("train.seed", type=int,
               help="seed of initialisation, shuffling and augmentation"),
    ConfigFlag("train.eval_every", type=positive_int, metavar="N",
               help="validate every N epochs (and after the last)"),
    ConfigFlag("train.select_metric", choices=SELECT_METRICS, help="best-model criterion"),
    ConfigFlag("train.workers", type=positive_int, help="data loading threads"),
)


def optimizer_help() -> str:
    """The ``--optimizer`` help: the two recipes' settings."""
    return (f"rmsprop: the paper (lr {_paper.lr:g}, momentum {_paper.momentum:g}, weight "
            f"decay {_paper.weight_decay:g}); sgd: YOLOv5's (lr {_sgd.lr:g}, Nesterov momentum "
            f"{_sgd.momentum:g}, weight decay {_sgd.weight_decay:g}, warmup, "
            f"{_sgd.lr_schedule} decay) [default: {_paper.optimizer}]")


def add_train_options(parser, flags: Sequence[ConfigFlag] = TRAIN_FLAGS,
                      defaults: Mapping[str, Any] | None = None) -> None:
    """``--optimizer`` and ``flags``, whose help states the paper recipe's values with
    ``defaults`` (``{key: value}``, a caller's own budget) applied."""
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default=_paper.optimizer,
                        help=optimizer_help())
    add_config_flags(parser, apply_overrides(DetectConfig(), defaults or {}), flags)


def train_options(args: argparse.Namespace, flags: Sequence[ConfigFlag] = TRAIN_FLAGS,
                  defaults: Mapping[str, Any] | None = None) -> DetectConfig:
    """The :class:`DetectConfig` of parsed options: the ``--optimizer`` recipe
    (:meth:`TrainConfig.paper` or :meth:`TrainConfig.yolov5`), then ``defaults``, then the
    options given (:func:`~uavcal_jax.argtypes.flag_overrides`)."""
    train = TrainConfig.yolov5() if args.optimizer == "sgd" else TrainConfig.paper()
    config = apply_overrides(DetectConfig(train=train), defaults or {})
    return apply_overrides(config, flag_overrides(args, flags))
