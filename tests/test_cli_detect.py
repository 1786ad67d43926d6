"""`uavcal detect train -> eval -> predict` on a tiny VOC folder made here."""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
import pytest

from uavcal_jax.cli import build_parser, main

pytestmark = pytest.mark.usefixtures("xla_cache")


def make_voc(root, n=6, seed=0, size=(72, 104)):
    """A VOC folder: n noisy images with filled rectangles (red / blue)."""
    rng = np.random.default_rng(seed)
    (root / "Annotations").mkdir(parents=True)
    (root / "JPEGImages").mkdir()
    h, w = size
    for i in range(n):
        img = (rng.random((h, w, 3)) * 60).astype(np.uint8)
        objects = []
        for _ in range(int(rng.integers(1, 3))):
            bw, bh = int(rng.integers(14, 36)), int(rng.integers(14, 30))
            x0, y0 = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
            name = "red" if rng.random() < 0.5 else "blue"
            cv2.rectangle(img, (x0, y0), (x0 + bw - 1, y0 + bh - 1),
                          (0, 0, 255) if name == "red" else (255, 0, 0), -1)
            objects.append(
                f"<object><name>{name}</name><difficult>0</difficult><bndbox>"
                f"<xmin>{x0 + 1}</xmin><ymin>{y0 + 1}</ymin><xmax>{x0 + bw}</xmax>"
                f"<ymax>{y0 + bh}</ymax></bndbox></object>")
        cv2.imwrite(str(root / "JPEGImages" / f"img{i}.jpg"), img)
        (root / "Annotations" / f"img{i}.xml").write_text(
            f"<annotation><filename>img{i}.jpg</filename><size><width>{w}</width>"
            f"<height>{h}</height><depth>3</depth></size>{''.join(objects)}</annotation>")
    return root


def _json_line(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


def test_help_on_every_action(capsys):
    for argv in (["detect", "--help"], ["detect", "train", "--help"],
                 ["detect", "eval", "--help"], ["detect", "predict", "--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
        assert "usage: uavcal detect" in capsys.readouterr().out


def _subparser(parser: argparse.ArgumentParser, *names: str) -> argparse.ArgumentParser:
    for name in names:
        (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        parser = sub.choices[name]
    return parser


def test_parser_defaults_are_the_dataclass_defaults():
    """Every option of `detect train/eval/predict` takes its default and choices from the
    configuration dataclasses and constants; a new option fails here until it is listed."""
    from uavcal_jax.commands.detect import PREDICT_BATCH, train_config
    from uavcal_jax.detect.augment import AugmentConfig
    from uavcal_jax.detect.config import (
        EVAL_PREDICT,
        MODELS,
        OPTIMIZERS,
        SCHEDULES,
        SELECT_METRICS,
        SERVE_PREDICT,
        DetectorConfig,
        TrainConfig,
    )
    from uavcal_jax.detect.datasets import FORMATS
    from uavcal_jax.detect.run import CHECKPOINTS

    paper = TrainConfig()
    # dest -> (default, choices); None choices: a free value
    expected = {
        "train": {
            "format": (None, FORMATS), "model": (DetectorConfig().model, MODELS),
            "epochs": (paper.epochs, None), "imgsz": (DetectorConfig().img_size, None),
            "batch": (paper.batch_size, None), "optimizer": (paper.optimizer, OPTIMIZERS),
            "lr": (None, None), "schedule": (None, SCHEDULES),
            "warmup_epochs": (paper.warmup_epochs, None),
            "no_augment": (paper.augment is None, None),
            "mosaic": (AugmentConfig().mosaic, None), "no_ema": (not paper.ema, None),
            "no_autoanchor": (not paper.autoanchor, None),
            "val_fraction": (paper.val_fraction, None), "split_seed": (paper.split_seed, None),
            "seed": (paper.seed, None), "eval_every": (paper.eval_every, None),
            "select_metric": (paper.select_metric, SELECT_METRICS),
            "workers": (paper.workers, None),
        },
        "eval": {
            "format": (None, FORMATS), "checkpoint": ("best", CHECKPOINTS),
            "conf": (EVAL_PREDICT.conf_thresh, None), "iou": (EVAL_PREDICT.iou_thresh, None),
            "batch": (paper.batch_size, None),
        },
        "predict": {
            "conf": (SERVE_PREDICT.conf_thresh, None), "iou": (SERVE_PREDICT.iou_thresh, None),
            "max_det": (SERVE_PREDICT.max_det, None), "batch": (PREDICT_BATCH, None),
        },
    }
    # options with no configuration field behind them: paths, run control, output format
    free = {"help", "data", "out", "run", "images", "checkpoint", "val_data", "max_steps",
            "resume", "no_export", "voc07", "json", "func"}
    parser = build_parser()
    for action_name, wanted in expected.items():
        sub = _subparser(parser, "detect", action_name)
        options = {a.dest: a for a in sub._actions}
        unchecked = set(options) - set(wanted) - free
        assert not unchecked, f"detect {action_name}: options without a checked default"
        for dest, (default, choices) in wanted.items():
            assert options[dest].default == default, (action_name, dest)
            assert (tuple(options[dest].choices) if options[dest].choices else None) == (
                tuple(choices) if choices else None), (action_name, dest)
    # the parsed defaults resolve to exactly the recipes' configurations
    argv = ["detect", "train", "--data", "d", "--out", "o"]
    assert train_config(parser.parse_args(argv)) == TrainConfig.paper()
    assert train_config(parser.parse_args([*argv, "--optimizer", "sgd"])) == TrainConfig.yolov5()
    assert TrainConfig().predict == EVAL_PREDICT


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["detect", "train", "--data", str(tmp_path / "nope"), "--out",
                 str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    assert main(["detect", "eval", str(tmp_path)]) == 2
    assert str(tmp_path) in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["detect", "train", "--data", str(tmp_path / "empty"), "--out",
                 str(tmp_path / "run")]) == 2
    assert "empty" in capsys.readouterr().err


def test_train_eval_predict_on_unseen_voc(tmp_path, capsys):
    data = make_voc(tmp_path / "voc")
    run = tmp_path / "run"
    rc = main(["detect", "train", "--data", str(data), "--format", "voc", "--out", str(run),
               "--epochs", "2", "--imgsz", "96x64", "--batch", "4", "--val-fraction", "0.25",
               "--no-augment", "--warmup-epochs", "0", "--schedule", "constant",
               "--workers", "1", "--json"])
    assert rc == 0
    summary = _json_line(capsys.readouterr().out)
    assert summary["epochs"] == 2 and summary["classes"] == ["blue", "red"]
    assert summary["num_train"] == 4 and summary["num_val"] == 2
    for name in ("config.json", "split.json", "metrics.csv", "metrics.json", "curves.png",
                 "export/detector.jax", "export/detector.jax.json"):
        assert (run / name).is_file(), name

    assert main(["detect", "eval", str(run), "--json"]) == 0
    ev = _json_line(capsys.readouterr().out)
    assert ev["num_images"] == 2
    assert 0.0 <= ev["map50_95"] <= ev["map50"] <= 1.0
    assert ev["map50"] == pytest.approx(summary["map50"], abs=1e-6)  # same split, same weights

    assert main(["detect", "eval", str(run), "--data", str(data), "--json"]) == 0
    ev_all = _json_line(capsys.readouterr().out)
    assert ev_all["num_images"] == 6 and set(ev_all) >= {"map50", "map50_95", "per_class"}

    assert main(["detect", "eval", str(run)]) == 0  # human-readable
    text = capsys.readouterr().out
    assert "map50 " in text and "map50_95 " in text

    out = tmp_path / "pred"
    (data / "JPEGImages" / "broken.jpg").write_bytes(b"garbage")
    with pytest.warns(UserWarning, match="broken.jpg"):
        rc = main(["detect", "predict", str(data / "JPEGImages"), "--checkpoint", str(run),
                   "--out", str(out), "--conf", "0.01", "--json"])
    assert rc == 0
    pred = _json_line(capsys.readouterr().out)
    assert pred["images"] == 6
    doc = json.loads((out / "detections.json").read_text())
    assert len(doc["images"]) == 6 and {c["name"] for c in doc["categories"]} == {"blue", "red"}
    for ann in doc["annotations"]:
        assert len(ann["bbox"]) == 4 and 0.01 <= ann["score"] <= 1.0
    assert cv2.imread(str(out / "img0.jpg")).shape == (72, 104, 3)
    # a glob works too
    assert main(["detect", "predict", str(data / "JPEGImages" / "img1.*"), "--checkpoint",
                 str(run), "--out", str(tmp_path / "pred1"), "--json"]) == 0
    assert _json_line(capsys.readouterr().out)["images"] == 1
