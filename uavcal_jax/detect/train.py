"""Training the detector: one pure jitted step, RMSprop (the paper) or YOLOv5's SGD, EMA,
orbax checkpoints with resume, and best-model selection on validation mAP.

The numerics are pure: :func:`make_train_step` returns ``step(state, images, targets) ->
(state, metrics)`` where ``state`` is a :class:`TrainState` pytree (params, BN statistics,
optimizer state, EMA of params and BN statistics, step count). Everything with side effects
(data loading, checkpoints, CSV/JSON/PNG outputs, progress bars) lives in :func:`train`.

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
rank >= 2) only. Gradients are clipped to a global norm of 10 (v7.0). The EMA follows
YOLOv5's ``ModelEMA``: ``d = decay * (1 - exp(-updates / tau))`` applied after every step to
params and BN statistics. YOLOv5's gradient accumulation to a nominal batch of 64 is not
reproduced (every batch is a step).

Best model: after each evaluation the EMA weights are scored on the validation split by
``TrainConfig.select_metric`` (default ``map50_95``; ``map50`` or YOLOv5's
``fitness = 0.1 map50 + 0.9 map50_95``) and the best are saved to ``checkpoints/best``.

Run folder::

    config.json     resolved detector + train config, data set info
    split.json      the train/val image ids (the fixed split; eval reuses it)
    metrics.csv     one row per epoch (losses, lr, map50, map50_95, time)
    metrics.json    the same rows, plus the best epoch and scores
    curves.png      loss and mAP curves
    checkpoints/last/<epoch>/  full train state + meta (resume)
    checkpoints/best/<epoch>/  EMA variables of the best epoch + meta
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from uavcal_jax.detect.anchors import check_anchors, label_sizes
from uavcal_jax.detect.augment import AugmentConfig, unletterbox_boxes
from uavcal_jax.detect.checkpoint import Checkpoints
from uavcal_jax.detect.config import DetectorConfig
from uavcal_jax.detect.datasets import (
    DetectionDataset,
    load_dataset,
    save_split,
    split_ids,
)
from uavcal_jax.detect.loader import DetectionLoader
from uavcal_jax.detect.metrics import MapResult, evaluate_detections, fitness
from uavcal_jax.detect.model import build_detector
from uavcal_jax.errors import DataError

OPTIMIZERS = ("rmsprop", "sgd")
SCHEDULES = ("constant", "linear", "cosine")
SELECT_METRICS = ("map50_95", "map50", "fitness")


@dataclass(frozen=True)
class TrainConfig:
    """Everything about a training run except the model (:class:`DetectorConfig`).

    The defaults are the paper's (RMSprop, lr 0.01, momentum 0.9, weight decay 1e-5,
    batch 8); :meth:`yolov5` gives YOLOv5's SGD recipe.
    """

    epochs: int = 100
    batch_size: int = 8
    optimizer: str = "rmsprop"
    lr: float = 0.01
    momentum: float = 0.9
    weight_decay: float = 1e-5
    rmsprop_decay: float = 0.9
    rmsprop_eps: float = 1e-3
    nesterov: bool = True
    lr_schedule: str = "cosine"
    lrf: float = 0.01
    warmup_epochs: float = 3.0
    warmup_min_steps: int = 100
    warmup_bias_lr: float = 0.1
    warmup_momentum: float = 0.8
    grad_clip: float = 10.0
    ema: bool = True
    ema_decay: float = 0.9999
    ema_tau: float = 2000.0
    seed: int = 0
    augment: AugmentConfig | None = field(default_factory=AugmentConfig)
    val_fraction: float = 0.2
    split_seed: int = 0
    eval_every: int = 1
    conf_thresh: float = 0.001
    iou_thresh: float = 0.6
    max_det: int = 300
    map_max_dets: int = 100
    select_metric: str = "map50_95"
    workers: int = 2
    cache: bool = True
    autoanchor: bool = True

    def __post_init__(self):
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, not {self.optimizer!r}")
        if self.lr_schedule not in SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {SCHEDULES}")
        if self.select_metric not in SELECT_METRICS:
            raise ValueError(f"select_metric must be one of {SELECT_METRICS}")
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError("epochs and batch_size must be >= 1")
        if isinstance(self.augment, dict):
            object.__setattr__(self, "augment", AugmentConfig(**self.augment))

    @classmethod
    def paper(cls, **changes) -> TrainConfig:
        """RPEOD section 6.2: RMSprop, lr 0.01, momentum 0.9, weight decay 1e-5, batch 8."""
        return cls(**changes)

    @classmethod
    def yolov5(cls, **changes) -> TrainConfig:
        """YOLOv5 v7.0 ``hyp.scratch-low``: Nesterov SGD, lr0 0.01, momentum 0.937, weight
        decay 5e-4, 3 warmup epochs, linear decay to lrf 0.01."""
        base = dict(optimizer="sgd", lr=0.01, momentum=0.937, weight_decay=5e-4,
                    lr_schedule="linear", lrf=0.01)
        return cls(**{**base, **changes})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        kw = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**kw)


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


# ----------------------------------------------------------------------------- optimiser


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


# ----------------------------------------------------------------------------- train step


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
    abstract = jax.eval_shape(lambda: init_variables(jax.random.PRNGKey(0), det_cfg))
    tx = make_optimizer(cfg, steps_per_epoch, abstract["params"])
    return tx, make_train_step(det_cfg, cfg, tx)


def make_train_step(det_cfg: DetectorConfig, cfg: TrainConfig, tx) -> Callable:
    """A jitted ``step(state, images, targets) -> (state, metrics)``."""
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
        metrics = {k: v for k, v in parts.items()}
        metrics["loss"] = loss
        metrics["grad_norm"] = optax.tree.norm(grads)
        return TrainState(n, params, stats, opt_state, ema_params, ema_stats), metrics

    return jax.jit(step, donate_argnums=(0,))


def current_lr(cfg: TrainConfig, steps_per_epoch: int, step: int) -> float:
    return float(make_schedules(cfg, steps_per_epoch)[0](step))


# ----------------------------------------------------------------------------- evaluation


@functools.lru_cache(maxsize=16)
def make_predict(det_cfg: DetectorConfig, conf_thresh: float = 0.001, iou_thresh: float = 0.6,
                 max_det: int = 300, multi_label: bool = True) -> Callable:
    """The jitted inference function ``fn(variables, images) -> Detections``.

    The defaults are YOLOv5 ``val.py``'s (conf 0.001, IoU 0.6, multi-label NMS) for mAP.
    """
    from uavcal_jax.detect.predict import make_predict_fn

    return make_predict_fn(det_cfg, conf_thresh=conf_thresh, iou_thresh=iou_thresh,
                           max_det=max_det, multi_label=multi_label)


def predict_dataset(predict_fn, variables, loader: DetectionLoader, progress=None
                    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Detections of every record of an (un-augmented) loader, in original image pixels:
    a list (by record) of ``(boxes (m, 4), scores (m,), classes (m,))``."""
    out: list = [None] * len(loader.records)
    batches = loader.epoch(0)
    if progress is not None:
        batches = progress(batches, total=len(loader))
    for batch in batches:
        det = predict_fn(variables, jnp.asarray(batch.images))
        boxes, scores = np.asarray(det.boxes), np.asarray(det.scores)
        classes, valid = np.asarray(det.classes), np.asarray(det.valid)
        for j, idx in enumerate(batch.indices):
            if idx < 0:
                continue
            rec = loader.records[idx]
            keep = valid[j].astype(bool)
            b = unletterbox_boxes(boxes[j][keep], float(batch.ratios[j]),
                                  tuple(batch.pads[j]), (rec.width, rec.height))
            out[idx] = (b, scores[j][keep].astype(np.float64),
                        classes[j][keep].astype(np.int64))
    return out


def evaluate_predictions(records, detections, num_classes: int, max_dets: int = 100,
                         interpolation: str = "coco101") -> MapResult:
    """mAP of per-record detections against the records' ground truth (difficult = ignore)."""
    return evaluate_detections(
        [r.boxes for r in records], [r.classes for r in records],
        [d[0] for d in detections], [d[1] for d in detections], [d[2] for d in detections],
        num_classes=num_classes, gt_ignore=[r.difficult for r in records], max_dets=max_dets,
        interpolation=interpolation)


# ----------------------------------------------------------------------------- the loop


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    keys = list(rows[0].keys())
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})


def plot_curves(path: Path, rows: list[dict], title: str = "") -> None:
    """Loss and mAP per epoch into a PNG (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [r["epoch"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    for key in ("loss", "box", "obj", "cls"):
        if any(key in r for r in rows):
            ax1.plot(epochs, [r.get(key, np.nan) for r in rows], label=key)
    ax1.set_xlabel("epoch")
    ax1.set_ylabel("train loss")
    ax1.set_yscale("log")
    ax1.legend()
    for key in ("map50", "map50_95"):
        xs = [r["epoch"] for r in rows if r.get(key) is not None]
        ax2.plot(xs, [r[key] for r in rows if r.get(key) is not None], "o-", label=key)
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("validation mAP")
    ax2.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def prepare_split(dataset: DetectionDataset, cfg: TrainConfig, val_dataset=None):
    """``(train, val)`` data sets: ``val_dataset`` if given, else the fixed split."""
    if val_dataset is not None:
        return dataset, val_dataset
    if cfg.val_fraction <= 0:
        return dataset, None
    train_ids, val_ids = split_ids(dataset.image_ids, cfg.val_fraction, cfg.split_seed)
    return dataset.subset(train_ids), dataset.subset(val_ids)


def _resolve_paths(run: Path) -> dict:
    return {"config": run / "config.json", "split": run / "split.json",
            "csv": run / "metrics.csv", "json": run / "metrics.json",
            "png": run / "curves.png", "last": run / "checkpoints" / "last",
            "best": run / "checkpoints" / "best"}


def train(dataset: DetectionDataset | str | Path, det_cfg: DetectorConfig, cfg: TrainConfig,
          out_dir: str | Path, *, resume: bool = False, val_dataset: DetectionDataset | None =
          None, data_format: str | None = None, progress: Callable | None = None,
          log: Callable[[str], None] | None = None, max_steps_per_epoch: int | None = None,
          stop_after: int | None = None) -> dict:
    """Train ``det_cfg`` on ``dataset`` with ``cfg``; write the run folder ``out_dir``.

    Args:
        dataset: a data set or a folder (read with ``data_format``, auto-detected).
        det_cfg: the model; ``num_classes`` is taken from the data set.
        resume: continue from ``out_dir/checkpoints/last`` (the saved config and split are
            used; ``cfg.epochs`` may be raised to train longer).
        val_dataset: evaluate on this instead of the fixed split.
        progress: ``progress(iterable, total=..., desc=...)`` wrapper (e.g. tqdm).
        log: called with one line per epoch.
        max_steps_per_epoch: cap batches per epoch (tests, smoke runs).
        stop_after: stop after this many epochs of this call (checkpoint written), as if
            interrupted; ``resume=True`` continues (the schedule is that of ``cfg.epochs``).

    Returns a summary dict: run folder, epochs, best epoch and its scores, final losses.
    """
    run = Path(out_dir)
    paths = _resolve_paths(run)
    if isinstance(dataset, str | Path):
        dataset = load_dataset(dataset, data_format)
    if len(dataset) == 0:
        raise DataError("the data set has no images", dataset.root)
    det_cfg = det_cfg.replace(num_classes=max(1, dataset.num_classes))
    if resume:
        if not paths["config"].is_file():
            raise DataError("nothing to resume (no config.json)", run)
        saved = json.loads(paths["config"].read_text())
        det_cfg = DetectorConfig.from_dict(saved["detector"])
        epochs = cfg.epochs
        cfg = dataclasses.replace(TrainConfig.from_dict(saved["train"]), epochs=epochs)
        split = json.loads(paths["split"].read_text()) if paths["split"].is_file() else None
        if split is not None and split.get("val") is not None and val_dataset is None:
            train_set = dataset.subset(split["train"])
            val_set = dataset.subset(split["val"]) if split["val"] else None
        else:
            train_set, val_set = prepare_split(dataset, cfg, val_dataset)
    else:
        train_set, val_set = prepare_split(dataset, cfg, val_dataset)
        wh = label_sizes(train_set, det_cfg.img_size)
        if cfg.autoanchor and len(wh):  # YOLOv5's train.py: fit anchors to the labels
            det_cfg, report = check_anchors(det_cfg, wh, seed=cfg.seed)
            if log is not None:
                log(json.dumps({"autoanchor": report}))
    run.mkdir(parents=True, exist_ok=True)
    config_doc = {
        "detector": det_cfg.to_dict(),
        "train": cfg.to_dict(),
        "data": {"root": str(Path(dataset.root).absolute()), "format": dataset.format,
                 "class_names": list(dataset.class_names),
                 "category_ids": list(dataset.category_ids),
                 "num_train": len(train_set), "num_val": len(val_set) if val_set else 0,
                 "external_val": val_dataset is not None},
    }
    paths["config"].write_text(json.dumps(config_doc, indent=1))
    if not (resume and paths["split"].is_file()):
        save_split(paths["split"], train_set.image_ids, val_set.image_ids if val_set else [],
                   val_fraction=cfg.val_fraction, seed=cfg.split_seed,
                   external_val=val_dataset is not None)

    loader = DetectionLoader(train_set, det_cfg.img_size, cfg.batch_size, augment=cfg.augment,
                             shuffle=True, seed=cfg.seed, drop_last=True, cache=cfg.cache,
                             workers=cfg.workers)
    steps_per_epoch = len(loader) if max_steps_per_epoch is None else min(
        len(loader), max_steps_per_epoch)
    val_loader = (DetectionLoader(val_set, det_cfg.img_size, cfg.batch_size, cache=cfg.cache,
                                  workers=cfg.workers, include_difficult=True)
                  if val_set is not None and len(val_set) else None)

    key = jax.random.PRNGKey(cfg.seed)
    # the step does not depend on the epoch budget except through the schedule
    tx, step_fn = compiled_training(det_cfg, cfg, steps_per_epoch)
    state0 = init_train_state(key, det_cfg, tx)
    last = Checkpoints(paths["last"], max_to_keep=1)
    best = Checkpoints(paths["best"], max_to_keep=1)
    history: list[dict] = []
    start_epoch, best_score, best_epoch = 0, -math.inf, None
    state = state0
    if resume and last.latest_step() is not None:
        state, meta = last.restore(state0)
        history = meta["history"]
        start_epoch = int(meta["epoch"]) + 1
        best_score = float(meta["best_score"]) if meta.get("best_score") is not None \
            else -math.inf
        best_epoch = meta.get("best_epoch")
        loader.load_state_dict(meta["loader"])
    loader.next_epoch = start_epoch

    predict_fn = make_predict(det_cfg, cfg.conf_thresh, cfg.iou_thresh, cfg.max_det) \
        if val_loader else None
    wrap = progress or (lambda it, **kw: it)

    try:
        end_epoch = cfg.epochs if stop_after is None else min(cfg.epochs,
                                                             start_epoch + stop_after)
        for epoch in range(start_epoch, end_epoch):
            t0 = time.perf_counter()
            sums: dict[str, float] = {}
            n = 0
            batches = loader.epoch(epoch)
            for b, batch in enumerate(wrap(batches, total=steps_per_epoch,
                                           desc=f"epoch {epoch + 1}/{cfg.epochs}")):
                if b >= steps_per_epoch:
                    break
                state, metrics = step_fn(state, jnp.asarray(batch.images),
                                         jnp.asarray(batch.targets))
                metrics = jax.device_get(metrics)
                for k, v in metrics.items():
                    sums[k] = sums.get(k, 0.0) + float(v)
                n += 1
            batches.close()
            loader.next_epoch = epoch + 1
            row: dict[str, Any] = {"epoch": epoch + 1,
                                   "lr": current_lr(cfg, steps_per_epoch,
                                                    int(state.step) - 1)}
            row.update({k: v / max(n, 1) for k, v in sums.items()})
            if not all(math.isfinite(row[k]) for k in sums):
                raise FloatingPointError(f"non-finite training loss at epoch {epoch + 1}: "
                                         f"{row}")
            row["train_time_s"] = time.perf_counter() - t0
            evaluate_now = val_loader is not None and (
                (epoch + 1) % cfg.eval_every == 0 or epoch + 1 == cfg.epochs)
            if evaluate_now:
                t1 = time.perf_counter()
                dets = predict_dataset(predict_fn, state.variables(cfg.ema), val_loader)
                result = evaluate_predictions(val_loader.records, dets, det_cfg.num_classes,
                                              cfg.map_max_dets)
                row["map50"], row["map50_95"] = result.map50, result.map50_95
                row["eval_time_s"] = time.perf_counter() - t1
                score = fitness(result, cfg.select_metric)
            else:
                score = None
            improved = (score is not None and score > best_score) or (
                val_loader is None and epoch + 1 == cfg.epochs)
            if improved:
                best_score = score if score is not None else best_score
                best_epoch = epoch + 1
            history.append(row)
            meta = {"epoch": epoch, "history": history,
                    "best_score": None if best_score == -math.inf else best_score,
                    "best_epoch": best_epoch, "loader": loader.state_dict(),
                    "steps_per_epoch": steps_per_epoch}
            if improved:
                best.save(epoch + 1, state.variables(cfg.ema),
                          {**meta, "select_metric": cfg.select_metric})
            last.save(epoch + 1, state, meta)
            _write_outputs(paths, history, best_epoch, best_score, cfg, det_cfg)
            if log is not None:
                shown = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}
                log(json.dumps(shown))
    finally:
        loader.close()
        if val_loader is not None:
            val_loader.close()
        last.close()
        best.close()

    if best_epoch is None and history and len(history) == cfg.epochs:
        # validation never ran: keep the last weights
        with Checkpoints(paths["best"], max_to_keep=1) as ck:
            ck.save(len(history), state.variables(cfg.ema), {"epoch": len(history) - 1,
                                                             "history": history})
            best_epoch = len(history)
    final = history[-1] if history else {}
    best_row = next((r for r in history if r["epoch"] == best_epoch), {})
    return {
        "run": str(run), "model": det_cfg.model, "epochs": len(history),
        "steps": int(state.step), "best_epoch": best_epoch,
        "select_metric": cfg.select_metric,
        "map50": best_row.get("map50"), "map50_95": best_row.get("map50_95"),
        "final_loss": final.get("loss"), "num_train": len(train_set),
        "num_val": len(val_set) if val_set else 0,
    }


def _write_outputs(paths, history, best_epoch, best_score, cfg, det_cfg) -> None:
    _write_csv(paths["csv"], history)
    paths["json"].write_text(json.dumps({
        "history": history, "best_epoch": best_epoch,
        "best_score": None if best_score == -math.inf else best_score,
        "select_metric": cfg.select_metric}, indent=1))
    try:
        plot_curves(paths["png"], history, title=det_cfg.model)
    except Exception as err:  # noqa: BLE001 - a plot must never stop training
        paths["png"].with_suffix(".txt").write_text(f"plot failed: {err}\n")


# ----------------------------------------------------------------------------- runs


@dataclass(frozen=True)
class LoadedRun:
    """A trained run read back: configs, data info, split and the best EMA variables."""

    run: Path
    det_cfg: DetectorConfig
    train_cfg: TrainConfig
    data: dict
    split: dict | None
    variables: dict
    meta: dict


def load_run(run: str | Path, which: str = "best") -> LoadedRun:
    """Read a run folder written by :func:`train` (``which``: ``"best"`` or ``"last"``)."""
    run = Path(run)
    paths = _resolve_paths(run)
    if not paths["config"].is_file():
        raise DataError("not a training run (no config.json)", run)
    doc = json.loads(paths["config"].read_text())
    det_cfg = DetectorConfig.from_dict(doc["detector"])
    train_cfg = TrainConfig.from_dict(doc["train"])
    split = json.loads(paths["split"].read_text()) if paths["split"].is_file() else None
    abstract = jax.eval_shape(lambda: init_variables(jax.random.PRNGKey(0), det_cfg))
    if which == "best":
        with Checkpoints(paths["best"], read_only=True) as ck:
            variables, meta = ck.restore(abstract)
    else:
        with Checkpoints(paths["last"], read_only=True) as ck:
            tx = make_optimizer(train_cfg, 1, abstract["params"])
            st_abs = jax.eval_shape(lambda: init_train_state(jax.random.PRNGKey(0), det_cfg,
                                                             tx))
            state, meta = ck.restore(st_abs)
            variables = state.variables(train_cfg.ema)
    return LoadedRun(run, det_cfg, train_cfg, doc["data"], split, variables, meta)
