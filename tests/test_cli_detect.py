"""`uavcal detect train -> eval -> predict` on a tiny VOC folder made here."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

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
    from uavcal_jax.commands.detect import PREDICT_BATCH
    from uavcal_jax.data.detection_labels import LABEL_FORMATS
    from uavcal_jax.detect.config import (
        EVAL_PREDICT,
        MODELS,
        OPTIMIZERS,
        SCHEDULES,
        SELECT_METRICS,
        SERVE_PREDICT,
        TrainConfig,
    )
    from uavcal_jax.detect.options import TRAIN_FLAGS, train_options
    from uavcal_jax.detect.tile import TILE_MODES, TileConfig
    from uavcal_jax.runs import KINDS

    paper = TrainConfig()
    tile = {"tile": ("auto", TILE_MODES), "tile_overlap": (TileConfig.overlap, None)}
    # dest -> (default, choices); None choices: a free value
    expected = {
        # the other train options set config fields: test_train_options_set_their_fields
        "train": {"format": (None, LABEL_FORMATS), "optimizer": (paper.optimizer, OPTIMIZERS),
                  **{f.dest: (argparse.SUPPRESS, f.choices) for f in TRAIN_FLAGS}},
        "eval": {
            "format": (None, LABEL_FORMATS), "checkpoint": ("best", KINDS),
            "conf": (EVAL_PREDICT.conf_thresh, None), "iou": (EVAL_PREDICT.iou_thresh, None),
            "batch": (paper.batch_size, None), **tile,
        },
        "predict": {
            "conf": (SERVE_PREDICT.conf_thresh, None), "iou": (SERVE_PREDICT.iou_thresh, None),
            "max_det": (SERVE_PREDICT.max_det, None), "batch": (PREDICT_BATCH, None),
            **tile,
        },
    }
    # options with no configuration field behind them: paths, run control, output format
    free = {"help", "data", "out", "run", "images", "checkpoint", "val_data", "max_steps",
            "resume", "no_export", "voc07", "json", "func",
            "set"}  # --set: any configuration field, after the options
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
    sgd = [*argv, "--optimizer", "sgd"]
    assert train_options(parser.parse_args(argv)).train == TrainConfig.paper()
    assert train_options(parser.parse_args(sgd)).train == TrainConfig.yolov5()
    assert TrainConfig().predict == EVAL_PREDICT
    choices = {f.key: tuple(f.choices) for f in TRAIN_FLAGS if f.choices}
    assert choices == {"detector.model": MODELS, "train.lr_schedule": SCHEDULES,
                       "train.select_metric": SELECT_METRICS}


def test_train_options_set_their_fields():
    """Each `detect train` option sets its field over the --optimizer recipe."""
    from uavcal_jax.detect.augment import AugmentConfig
    from uavcal_jax.detect.config import DetectConfig, DetectorConfig, TrainConfig
    from uavcal_jax.detect.options import train_options

    parser = build_parser()
    base = ["detect", "train", "--data", "d", "--out", "o"]
    argv = [*base, "--model", "yznet-yolo", "--epochs", "7", "--imgsz", "320x256", "--batch",
            "4", "--lr", "0.02", "--schedule", "linear", "--warmup-epochs", "0", "--mosaic",
            "0.5", "--no-ema", "--no-autoanchor", "--val-fraction", "0.3", "--split-seed", "2",
            "--seed", "3", "--eval-every", "2", "--select-metric", "map50", "--workers", "1"]
    changes = dict(epochs=7, batch_size=4, lr=0.02, lr_schedule="linear", warmup_epochs=0.0,
                   augment=AugmentConfig(mosaic=0.5), ema=False, autoanchor=False,
                   val_fraction=0.3, split_seed=2, seed=3, eval_every=2,
                   select_metric="map50", workers=1)
    detector = DetectorConfig(model="yznet-yolo", img_size=(256, 320))
    assert train_options(parser.parse_args(argv)) == DetectConfig(
        detector, TrainConfig.paper(**changes))
    assert train_options(parser.parse_args([*argv, "--optimizer", "sgd"])) == DetectConfig(
        detector, TrainConfig.yolov5(**changes))
    assert train_options(parser.parse_args([*argv, "--no-augment"])).train == TrainConfig.paper(
        **{**changes, "augment": None})


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


@pytest.mark.heavy
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


# ------------------------------------------------------------------ --set (no training)


def _fake_run(root, **train_changes):
    """A run folder holding only config.json (what eval and predict read first)."""
    from uavcal_jax.detect.config import DetectorConfig, TrainConfig
    from uavcal_jax.detect.run import RunPaths, write_config

    root.mkdir(parents=True)
    write_config(RunPaths(root), DetectorConfig(num_classes=2), TrainConfig(**train_changes),
                 {"root": str(root), "format": "voc", "class_names": ["blue", "red"],
                  "category_ids": [0, 1]})
    return root


def test_set_unknown_key_exits_2_naming_it(tmp_path, capsys):
    run = _fake_run(tmp_path / "run")
    for argv in (["train", "--data", str(tmp_path), "--out", str(tmp_path / "new")],
                 ["eval", str(run)],
                 ["predict", str(tmp_path), "--checkpoint", str(run), "--out",
                  str(tmp_path / "pred")]):
        assert main(["detect", *argv, "--set", "no_such_key=1"]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no_such_key" in err[0], argv
    assert not (tmp_path / "new").exists() and not (tmp_path / "pred").exists()


def test_train_set_applies_after_the_options(tmp_path, monkeypatch, capsys):
    import uavcal_jax.detect.train as train_module
    from uavcal_jax.detect.config import DetectConfig, DetectorConfig, TrainConfig
    from uavcal_jax.detect.run import RunPaths, read_config, write_config

    seen = {}

    def fake_train(dataset, det_cfg, cfg, out_dir, **kwargs):
        seen.update(det_cfg=det_cfg, cfg=cfg)
        write_config(RunPaths(tmp_path / "run"), det_cfg, cfg, {"class_names": []})
        return {"model": det_cfg.model, "epochs": 0, "map50": None}

    monkeypatch.setattr(train_module, "train", fake_train)
    data = make_voc(tmp_path / "voc", n=2)
    assert main(["detect", "train", "--data", str(data), "--out", str(tmp_path / "run"),
                 "--epochs", "7", "--mosaic", "0.5", "--no-export", "--json", "--set",
                 "train.epochs=3", "detector.anchor_t=3.5", "--set",
                 "train.augment.scale=0.25", "train.predict.conf_thresh=0.01"]) == 0
    capsys.readouterr()
    det_cfg, cfg = seen["det_cfg"], seen["cfg"]
    assert (cfg.epochs, cfg.augment.mosaic, cfg.augment.scale, cfg.predict.conf_thresh) == (
        3, 0.5, 0.25, 0.01)
    assert det_cfg.anchor_t == 3.5 and det_cfg.num_classes == 2  # from the data set
    # config.json (train's writer) reads back as the resolved configuration
    assert read_config(RunPaths(tmp_path / "run"))[0] == DetectConfig(det_cfg, cfg)
    assert TrainConfig.paper() == read_config(RunPaths(_fake_run(tmp_path / "plain")))[0].train
    assert DetectorConfig(num_classes=2) == read_config(RunPaths(tmp_path / "plain"))[0].detector


def test_eval_and_predict_write_their_resolved_config(tmp_path, monkeypatch, capsys):
    import importlib
    from types import SimpleNamespace

    import uavcal_jax.detect.annotate as annotate_module
    import uavcal_jax.detect.evaluate as evaluate_module
    import uavcal_jax.detect.run as run_module
    from uavcal_jax.config import read_config
    from uavcal_jax.detect.config import DetectorConfig, PredictConfig
    from uavcal_jax.detect.tile import TileConfig

    run = _fake_run(tmp_path / "run")
    seen = {}

    def fake_evaluate(run, data, fmt, **kwargs):
        seen["eval"] = kwargs
        return {"map50": 0.5, "map50_95": 0.25, "per_class": {}, "num_images": 1,
                "data": "d"}

    monkeypatch.setattr(evaluate_module, "evaluate_run", fake_evaluate)
    assert main(["detect", "eval", str(run), "--conf", "0.2", "--json", "--set",
                 "multi_label=false", "max_det=50"]) == 0
    out = _json_line(capsys.readouterr().out)
    resolved = read_config(run / "eval_config.json", PredictConfig,
                           ignore=("checkpoint", "data", "format", "batch", "interpolation",
                                   "tile"))
    assert out["config"] == str(run / "eval_config.json")
    assert resolved == PredictConfig(conf_thresh=0.2, iou_thresh=0.6, multi_label=False,
                                     max_det=50)
    assert PredictConfig(**{k: seen["eval"][k] for k in vars(resolved)}) == resolved
    assert seen["eval"]["tile"] == TileConfig.of_mode("auto")  # large images only, by default
    assert main(["detect", "eval", str(run), "--tile", "--tile-overlap", "0.3", "--out",
                 str(tmp_path / "ev"), "--json"]) == 0
    capsys.readouterr()
    assert seen["eval"]["tile"] == TileConfig(overlap=0.3)
    assert json.loads((tmp_path / "ev" / "eval_config.json").read_text())["tile"][
        "overlap"] == 0.3
    assert main(["detect", "eval", str(run), "--tile", "--tile-overlap", "1"]) == 2
    assert "--tile-overlap" in capsys.readouterr().err

    def fake_annotate(predict_fn, paths, img_size, out_dir, class_names, **kwargs):
        seen["info"], seen["tile"] = kwargs["info"], kwargs["tile"]
        return {"out": str(out_dir), "images": len(paths), "detections": 0}

    monkeypatch.setattr(run_module, "load_run", lambda run: SimpleNamespace(
        det_cfg=DetectorConfig(num_classes=2), variables={}, data={"class_names": ["a", "b"]}))
    # the module (the package's ``predict`` attribute is the function of that name)
    predict_module = importlib.import_module("uavcal_jax.detect.predict")
    monkeypatch.setattr(predict_module, "make_predict_fn", lambda det_cfg, cfg: print)
    monkeypatch.setattr(annotate_module, "annotate_files", fake_annotate)
    images = make_voc(tmp_path / "voc", n=1) / "JPEGImages"
    pred = tmp_path / "pred"
    assert main(["detect", "predict", str(images), "--checkpoint", str(run), "--out", str(pred),
                 "--iou", "0.3", "--json", "--set", "conf_thresh=0.05", "agnostic=true"]) == 0
    capsys.readouterr()
    resolved = read_config(pred / "predict_config.json", PredictConfig,
                           ignore=("checkpoint", "batch", "tile"))
    assert resolved == PredictConfig(conf_thresh=0.05, iou_thresh=0.3, agnostic=True)
    assert (seen["info"]["conf_thresh"], seen["info"]["iou_thresh"]) == (0.05, 0.3)
    assert seen["tile"] == TileConfig.of_mode("auto")
    assert main(["detect", "predict", str(images), "--checkpoint", str(run), "--out", str(pred),
                 "--tile", "off", "--json"]) == 0
    capsys.readouterr()
    assert seen["tile"] is None
    assert main(["detect", "predict", str(images), "--checkpoint", str(run), "--out", str(pred),
                 "--tile", "--json"]) == 0
    capsys.readouterr()
    assert seen["tile"] == TileConfig()
    assert json.loads((pred / "predict_config.json").read_text())["tile"] == vars(TileConfig())


# ------------------------------------------------------- evaluations never write the package


def _tree_bytes(root) -> dict:
    """Every file under ``root`` by relative path, with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def make_yolo(root, n=2, size=(96, 128)):
    """A YOLO folder whose classes.txt names car: n images, one grey box each."""
    root.mkdir(parents=True)
    (root / "classes.txt").write_text("car\n")
    h, w = size
    for i in range(n):
        img = np.full((h, w, 3), 90, np.uint8)
        cv2.rectangle(img, (20 + 10 * i, 30), (70 + 10 * i, 60), (200, 200, 200), -1)
        cv2.imwrite(str(root / f"img{i}.png"), img)
        cx, cy = (45.5 + 10 * i) / w, 45.5 / h
        (root / f"img{i}.txt").write_text(f"0 {cx:.5f} {cy:.5f} {51 / w:.5f} {31 / h:.5f}\n")
    return root


def test_eval_of_the_shipped_weights_never_writes_the_package(tmp_path, monkeypatch, capsys):
    from uavcal_jax.detect.default_weights import DEFAULT_DETECTOR_RUN

    data = make_yolo(tmp_path / "yolo", n=1)
    before = _tree_bytes(DEFAULT_DETECTOR_RUN)
    out = tmp_path / "mine"
    assert main(["detect", "eval", str(DEFAULT_DETECTOR_RUN), "--data", str(data), "--format",
                 "yolo", "--out", str(out), "--batch", "1", "--json"]) == 0
    ev = _json_line(capsys.readouterr().out)
    assert ev["num_images"] == 1 and ev["out"] == str(out / "eval.json")
    assert json.loads((out / "eval.json").read_text())["map50"] == ev["map50"]
    assert (out / "eval_config.json").is_file() and ev["config"] == str(
        out / "eval_config.json")
    # without --out: a folder of the user's own in the current folder, said on stderr
    monkeypatch.chdir(tmp_path)
    assert main(["detect", "eval", str(DEFAULT_DETECTOR_RUN), "--data", str(data), "--format",
                 "yolo", "--batch", "1", "--json"]) == 0
    captured = capsys.readouterr()
    home = tmp_path / "uavcal_eval" / "default"
    assert "uavcal_eval/default" in captured.err and "package" in captured.err
    assert {p.name for p in home.iterdir()} == {"eval.json", "eval_config.json"}
    assert json.loads((home / "eval.json").read_text())["map50"] == ev["map50"]
    assert _tree_bytes(DEFAULT_DETECTOR_RUN) == before


def test_results_folder_rule(tmp_path, monkeypatch):
    import uavcal_jax
    from uavcal_jax.calib.pretrained import DEFAULT_WEIGHTS
    from uavcal_jax.runs import EVAL_HOME, results_folder, results_redirect

    mine = tmp_path / "run"
    mine.mkdir()
    assert results_redirect(mine) is None and results_folder(mine) == mine
    assert results_folder(mine, tmp_path / "o") == tmp_path / "o"
    for shipped in (DEFAULT_WEIGHTS, Path(uavcal_jax.__file__).parent / "detect"):
        assert "package" in results_redirect(shipped)
        assert results_folder(shipped) == EVAL_HOME / shipped.name
    monkeypatch.setattr("os.access", lambda path, mode: False)  # read-only, as for a CD
    assert "not writable" in results_redirect(mine)
    assert results_folder(mine) == EVAL_HOME / "run"
