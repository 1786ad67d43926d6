"""The detector weights shipped in the package (``uavcal_jax/detect/weights/default``, made by
``experiments/detector_default_weights.py``): they restore as a run, are a few MB, and find a
target on a frame of a freshly simulated flight none of their training flights used."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from uavcal_jax.detect.default_weights import SHIPPED, default_detector_run
from uavcal_jax.errors import DataError

#: The weights' size on disk must stay under this (bytes): "a few MB at most".
MAX_BYTES = 5_000_000
#: mAP@0.5 the shipped weights must pass on four of the real aerial photos' held-out split.
MIN_AERIAL_MAP50 = 0.3


@pytest.fixture(scope="module")
def shipped():
    """The restored shipped run; skips when this checkout has no weights."""
    try:
        run = default_detector_run()
    except DataError as e:
        pytest.skip(f"no shipped detector weights ({e}); make them with "
                    "experiments/detector_default_weights.py")
    from uavcal_jax.detect.run import load_run

    return run, load_run(run)


def test_missing_weights_name_the_folder(monkeypatch, tmp_path):
    from uavcal_jax.detect import default_weights

    monkeypatch.setattr(default_weights, "DEFAULT_DETECTOR_RUN", tmp_path / "absent")
    with pytest.raises(DataError, match="absent: the shipped detector weights are missing"):
        default_weights.default_detector_run()


def test_shipped_run_restores_and_is_small(shipped):
    run, loaded = shipped
    size = sum(p.stat().st_size for p in run.rglob("*") if p.is_file())
    assert size < MAX_BYTES, f"{run} holds {size / 1e6:.2f} MB"
    assert loaded.det_cfg.model == SHIPPED.detector.model
    assert loaded.det_cfg.img_size == SHIPPED.detector.img_size
    assert tuple(loaded.data["class_names"]) == ("car", "person")
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(loaded.variables))


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of one box ``a`` (4,) with boxes ``b`` (n, 4), ``x_min, y_min, x_max, y_max``."""
    lo, hi = np.maximum(a[:2], b[:, :2]), np.minimum(a[2:], b[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = lambda x: (x[..., 2] - x[..., 0]) * (x[..., 3] - x[..., 1])  # noqa: E731
    return inter / (area(a) + area(b) - inter)


def test_finds_a_target_on_a_fresh_flight(shipped, tmp_path):
    import cv2

    from uavcal_jax.data.detection_records import IMREAD_FLAGS
    from uavcal_jax.detect.config import SERVE_PREDICT
    from uavcal_jax.detect.datasets import load_dataset
    from uavcal_jax.detect.predict import detect_images, make_predict_fn
    from uavcal_jax.sim.config import SimConfig
    from uavcal_jax.sim.simulate import simulate

    _, loaded = shipped
    # a procedural flight of a seed no training flight flies (they start at 2000), EuRoC's
    # 752x480 camera model, one moving target placed in view; frames 0.25 s apart
    folder = simulate(SimConfig(duration=0.6, seed=7, camera_rate_hz=5.0, depth=False,
                                follow_targets=1, batch_size=4), tmp_path / "flight",
                      progress=False)
    ds = load_dataset(folder, "sim", loaded.data["class_names"])
    # the largest labelled target clear of the image border (a box of visible pixels cut by
    # the border is a part of the target)
    best = None
    for r in ds.records:
        for box, cls in zip(r.boxes, r.classes, strict=True):
            inside = box[0] > 1 and box[1] > 1 and box[2] < r.width - 1 and box[3] < r.height - 1
            area = (box[2] - box[0]) * (box[3] - box[1])
            if inside and (best is None or area > best[0]):
                best = (area, r, box, int(cls))
    assert best is not None, "the simulated flight shows no whole target"
    _, record, box, cls = best
    image = cv2.cvtColor(cv2.imread(str(record.image_path), IMREAD_FLAGS), cv2.COLOR_BGR2RGB)
    fn = functools.partial(make_predict_fn(loaded.det_cfg, SERVE_PREDICT), loaded.variables)
    (det,) = detect_images(fn, [image], loaded.det_cfg.img_size)
    same = det.classes == cls
    ious = _iou(np.asarray(box, float), det.boxes[same]) if same.any() else np.zeros(0)
    assert ious.size and ious.max() > 0.5, (
        f"{record.image_id}: {loaded.data['class_names'][cls]} at {box} not found; "
        f"detections {det.boxes.round(1).tolist()} classes {det.classes.tolist()} scores "
        f"{det.scores.round(2).tolist()}")


def test_concat_datasets_keeps_ids_apart_and_maps_classes(tmp_path):
    from uavcal_jax.data.detection_records import DetectionDataset, DetectionRecord
    from uavcal_jax.detect.datasets import concat_datasets

    def one(root, class_names, cls):
        rec = DetectionRecord(root / "cam0" / "1.png", np.array([[1, 2, 30, 40]], np.float32),
                              np.array([cls], np.int32), np.zeros(1, bool), 752, 480,
                              "cam0/1.png")
        return DetectionDataset((rec,), class_names, root, "sim")

    a = one(tmp_path / "a", ("car", "person"), 1)
    b = one(tmp_path / "b", ("person", "car"), 0)  # another class order: person first
    ds = concat_datasets([("a", a), ("b", b)])
    assert ds.image_ids == ["a/cam0/1.png", "b/cam0/1.png"]
    assert ds.class_names == ("car", "person")
    assert [int(r.classes[0]) for r in ds.records] == [1, 1]  # both are persons
    assert ds.root == tmp_path and ds.format == "sim"
    with pytest.raises(ValueError, match="unique"):
        concat_datasets([("a", a), ("a", b)])


@pytest.mark.realdata
def test_finds_real_cars_in_the_held_out_aerial_photos(shipped, tmp_path):
    """The real aerial photos' held-out split (never trained on), sliced as ``--tile``
    slices them, scored by COCO mAP@0.5 (pycocotools-checked in test_detect_metrics)."""
    from tests.conftest import shared_path
    from uavcal_jax.detect.datasets import load_dataset, split_ids
    from uavcal_jax.detect.evaluate import evaluate_run
    from uavcal_jax.detect.tile import TileConfig

    run, loaded = shipped
    aerial = load_dataset(shared_path("detection", "aerial_cars_kit"), "yolo",
                          loaded.data["class_names"])
    held_out = aerial.subset(split_ids(aerial.image_ids, 0.2, 0)[1][:4])
    result = evaluate_run(run, held_out, tile=TileConfig(), out_dir=tmp_path)
    assert result["map50"] > MIN_AERIAL_MAP50, result


@pytest.mark.realdata
def test_sees_no_target_in_the_real_euroc_room(shipped):
    """The real EuRoC frames show a room with no car and no person: nothing at the run's
    threshold (the old weights boxed a mattress as a car at 0.5)."""
    from tests.conftest import shared_path
    from uavcal_jax.pipeline.detector_sources import false_positives

    run, _ = shipped
    frames = sorted(shared_path("euroc_v101_micro", "mav0", "cam0", "data").glob("*.png"))
    found = false_positives(run, frames[::12])
    assert found["frames"] == len(frames[::12]) > 0
    assert found["frames_with_any"] == 0 and found["per_frame"] == 0.0, found
