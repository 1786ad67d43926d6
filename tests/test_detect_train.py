"""Detector training: schedules, a tiny run whose loss falls, exact resume, export."""

from __future__ import annotations

import dataclasses
import functools
import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.detect.anchors import anchor_metrics, label_sizes
from uavcal_jax.detect.config import SERVE_PREDICT, DetectorConfig, TrainConfig
from uavcal_jax.detect.datasets import load_dataset
from uavcal_jax.detect.optim import (
    decay_mask,
    make_optimizer,
    make_schedules,
    param_labels,
    warmup_steps,
)
from uavcal_jax.detect.run import load_run
from uavcal_jax.detect.train import initial_state, starting_weights, train
from uavcal_jax.errors import DataError
from uavcal_jax.plots import training_curves_writer

IMG = (64, 96)  # (H, W): tiny, multiples of 32


pytestmark = pytest.mark.usefixtures("xla_cache")


def make_synthetic_yolo(root, n=8, seed=0, size=(72, 104)):
    """A YOLO folder of noisy images with filled rectangles: class 0 red, class 1 blue."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    (root / "classes.txt").write_text("red\nblue\n")
    h, w = size
    for i in range(n):
        img = (rng.random((h, w, 3)) * 60).astype(np.uint8)
        lines = []
        for _ in range(int(rng.integers(1, 3))):
            bw, bh = int(rng.integers(14, 36)), int(rng.integers(14, 30))
            x0, y0 = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
            c = int(rng.integers(0, 2))
            cv2.rectangle(img, (x0, y0), (x0 + bw - 1, y0 + bh - 1),
                          (0, 0, 255) if c == 0 else (255, 0, 0), -1)
            lines.append(f"{c} {(x0 + bw / 2) / w} {(y0 + bh / 2) / h} {bw / w} {bh / h}")
        cv2.imwrite(str(root / f"{i:03d}.png"), img)
        (root / f"{i:03d}.txt").write_text("\n".join(lines) + "\n")
    return root


def tiny_config(**changes) -> TrainConfig:
    base = dict(epochs=4, batch_size=4, warmup_epochs=0, augment=None, workers=1,
                val_fraction=0.25, lr_schedule="constant")
    return TrainConfig.paper(**{**base, **changes})


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    """One uninterrupted 4-epoch run and one stopped after 2 epochs and resumed."""
    root = make_synthetic_yolo(tmp_path_factory.mktemp("data") / "set", n=6)
    ds = load_dataset(root)
    det = DetectorConfig(model="yznet-yolo-tiny", img_size=IMG)
    cfg = tiny_config()
    run_a = tmp_path_factory.mktemp("run_a")
    run_b = tmp_path_factory.mktemp("run_b")
    summary_a = train(ds, det, cfg, run_a, on_epoch=training_curves_writer(run_a / "curves.png"))
    partial = train(ds, det, cfg, run_b, stop_after=2)
    summary_b = train(ds, det, cfg, run_b, resume=True)
    return ds, det, cfg, run_a, run_b, summary_a, partial, summary_b


def test_schedules_and_parameter_groups():
    cfg = TrainConfig.yolov5(epochs=10)
    lr_other, lr_bias, mom = make_schedules(cfg, steps_per_epoch=50)
    nw = warmup_steps(cfg, 50)
    assert nw == 150  # max(3 epochs, 100 steps)
    assert float(lr_bias(0)) == pytest.approx(0.1) and float(lr_other(0)) == 0.0
    assert float(mom(0)) == pytest.approx(0.8) and float(mom(nw)) == pytest.approx(0.937)
    # after warmup: lr0 * lf(epoch), linear to lrf
    assert float(lr_other(200)) == pytest.approx(0.01 * ((1 - 4 / 10) * 0.99 + 0.01))
    assert float(lr_bias(200)) == pytest.approx(float(lr_other(200)))
    paper = TrainConfig.paper(epochs=10)
    assert (paper.optimizer, paper.lr, paper.momentum, paper.weight_decay,
            paper.batch_size) == ("rmsprop", 0.01, 0.9, 1e-5, 8)
    lo, lb, m = make_schedules(paper, 50)
    assert float(lb(0)) == 0.0 and float(m(0)) == pytest.approx(0.9)
    params = {"conv": {"kernel": jnp.ones((3, 3, 4, 8)), "bias": jnp.ones(8)},
              "bn": {"scale": jnp.ones(8), "bias": jnp.zeros(8)}}
    assert decay_mask(params) == {"conv": {"kernel": True, "bias": False},
                                  "bn": {"scale": False, "bias": False}}
    assert param_labels(params)["bn"] == {"scale": "other", "bias": "bias"}


def test_tiny_training_loss_falls_and_writes_the_run(tiny_runs):
    ds, det, cfg, run_a, _, summary, _, _ = tiny_runs
    hist = json.loads((run_a / "metrics.json").read_text())["history"]
    losses = [r["loss"] for r in hist]
    assert len(losses) == 4 and all(np.isfinite(losses))
    assert losses[-1] < losses[0]
    assert all(0.0 <= r["map50"] <= 1.0 and r["map50_95"] <= r["map50"] for r in hist)
    for name in ("config.json", "split.json", "metrics.csv", "curves.png"):
        assert (run_a / name).is_file(), name
    split = json.loads((run_a / "split.json").read_text())
    assert len(split["val"]) == 2 and len(split["train"]) == 4
    config = json.loads((run_a / "config.json").read_text())
    assert config["train"]["optimizer"] == "rmsprop"
    assert config["data"]["class_names"] == ["red", "blue"]
    assert summary["epochs"] == 4 and summary["best_epoch"] in (1, 2, 3, 4)
    loaded = load_run(run_a)
    assert loaded.det_cfg.num_classes == 2 and loaded.det_cfg.img_size == IMG
    # autoanchor: the saved anchors recall the training labels at least as well as the
    # defaults, and replace them only when the defaults recall less than 98 %
    wh = label_sizes(ds.subset(split["train"]), IMG)
    bpr_default, bpr_saved = (anchor_metrics(a, wh)[0] for a in (det.anchors,
                                                                  loaded.det_cfg.anchors))
    assert bpr_saved >= bpr_default
    assert (tuple(map(tuple, loaded.det_cfg.anchors)) == tuple(map(tuple, det.anchors))) == (
        bpr_default >= 0.98)


def test_resume_reproduces_uninterrupted_run(tiny_runs):
    _, _, _, run_a, run_b, summary_a, partial, summary_b = tiny_runs
    assert partial["epochs"] == 2 and summary_b["epochs"] == 4
    a, b = load_run(run_a, "last"), load_run(run_b, "last")
    assert a.meta["epoch"] == b.meta["epoch"] == 4
    la = jax.tree.leaves(a.variables)
    lb = jax.tree.leaves(b.variables)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    ha = json.loads((run_a / "metrics.json").read_text())["history"]
    hb = json.loads((run_b / "metrics.json").read_text())["history"]
    np.testing.assert_allclose([r["loss"] for r in ha], [r["loss"] for r in hb], rtol=1e-5)


@pytest.mark.heavy  # CI budget: 80 s compiling the exported model again
def test_export_matches_in_process(tiny_runs, tmp_path):
    from uavcal_jax.detect.export import export_predict, load_exported
    from uavcal_jax.detect.predict import detect_images, make_predict_fn

    ds, det, _, run_a, *_ = tiny_runs
    loaded = load_run(run_a)
    predict_cfg = SERVE_PREDICT.replace(conf_thresh=0.001, iou_thresh=0.6)
    path = export_predict(loaded.variables, loaded.det_cfg, tmp_path / "det.jax",
                          class_names=ds.class_names, predict_cfg=predict_cfg)
    served = load_exported(path)
    assert served.meta["class_names"] == ["red", "blue"]
    images = jax.random.uniform(jax.random.PRNGKey(0), (2, *IMG, 3))
    out = served(images)
    ref = make_predict_fn(loaded.det_cfg, predict_cfg)(loaded.variables, images)
    np.testing.assert_array_equal(out["valid"], np.asarray(ref.valid))
    assert out["valid"].sum() > 0
    np.testing.assert_allclose(out["boxes"], np.asarray(ref.boxes), atol=1e-3)
    np.testing.assert_allclose(out["scores"], np.asarray(ref.scores), atol=1e-5)
    np.testing.assert_array_equal(out["classes"], np.asarray(ref.classes))
    image = (np.asarray(images[0]) * 255).astype(np.uint8)[:50, :80]  # letterboxed into IMG
    one = served.detect(image)
    assert one["boxes"].shape[1] == 4
    # the in-process predict path (as `uavcal detect predict`) gives the same boxes
    fn = functools.partial(make_predict_fn(loaded.det_cfg, predict_cfg), loaded.variables)
    (mine,) = detect_images(fn, [image], loaded.det_cfg.img_size)
    np.testing.assert_allclose(one["boxes"], mine.boxes, atol=1e-2)
    np.testing.assert_allclose(one["scores"], mine.scores, atol=1e-5)
    np.testing.assert_array_equal(one["classes"], mine.classes)
    assert np.all(mine.boxes[:, [0, 2]] <= 80) and np.all(mine.boxes[:, [1, 3]] <= 50)


def test_fine_tuning_starts_from_the_runs_weights(tiny_runs, tmp_path):
    """``init_from``: a fresh run's state holds the source run's best weights (as weights and
    as their EMA) and its model, whatever model was asked for; a data set naming other classes
    is refused before any training."""
    ds, det, cfg, run_a, *_ = tiny_runs
    tuned_cfg = dataclasses.replace(cfg, init_from=str(run_a))
    det_cfg, variables = starting_weights(tuned_cfg, ds)
    source = load_run(run_a)
    assert det_cfg == source.det_cfg != det.replace(img_size=(96, 128))
    tx = make_optimizer(tuned_cfg, 1, variables["params"])
    state = initial_state(det_cfg, tuned_cfg, tx, variables)
    fresh = initial_state(det_cfg, tuned_cfg, tx, None)
    for tree in (state.params, state.ema_params):
        for x, y, z in zip(jax.tree.leaves(tree), jax.tree.leaves(source.variables["params"]),
                           jax.tree.leaves(fresh.params), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
            assert x.shape == z.shape
    moved = [not np.array_equal(np.asarray(y), np.asarray(z)) for y, z in zip(
        jax.tree.leaves(source.variables["params"]), jax.tree.leaves(fresh.params), strict=True)]
    assert any(moved)  # the source run trained: its weights are not the random ones

    other = make_synthetic_yolo(tmp_path / "other", n=4)
    (other / "classes.txt").write_text("green\nblue\n")
    with pytest.raises(DataError, match="classes"):
        train(load_dataset(other), det, tuned_cfg, tmp_path / "refused")
