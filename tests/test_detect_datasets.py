"""Detection data: VOC/YOLO/COCO/simulator readers, bad input, split, augmentation, loader."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest

from tests.conftest import shared_path
from uavcal_jax.data.detection_labels import read_coco, read_sim_targets, read_voc, read_yolo
from uavcal_jax.detect.augment import (
    AugmentConfig,
    hflip,
    letterbox,
    mosaic4,
    random_affine,
    random_crop,
    scale_boxes,
    unletterbox_boxes,
)
from uavcal_jax.detect.datasets import class_index, detect_format, load_dataset, split_ids
from uavcal_jax.detect.loader import DetectionLoader
from uavcal_jax.errors import DataError, DataRepairWarning

# ------------------------------------------------------------------------------ helpers


def _image(path, w=64, h=48, boxes=()):
    img = np.full((h, w, 3), 40, np.uint8)
    for x0, y0, x1, y1 in boxes:
        cv2.rectangle(img, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), (220, 200, 30), -1)
    cv2.imwrite(str(path), img)


def _voc_xml(filename, objects, w=64, h=48):
    objs = "".join(
        f"<object><name>{n}</name><difficult>{d}</difficult><bndbox><xmin>{b[0]}</xmin>"
        f"<ymin>{b[1]}</ymin><xmax>{b[2]}</xmax><ymax>{b[3]}</ymax></bndbox></object>"
        for n, b, d in objects)
    return (f"<annotation><filename>{filename}</filename><size><width>{w}</width>"
            f"<height>{h}</height><depth>3</depth></size>{objs}</annotation>")


def _caught(fn, *args, **kw):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out = fn(*args, **kw)
    repair = [w for w in rec if issubclass(w.category, DataRepairWarning)]
    return out, repair


# ------------------------------------------------------------------------------ real data


@pytest.mark.realdata
def test_aerial_cars_kit_counts():
    root = shared_path("detection", "aerial_cars_kit")
    ds, warns = _caught(load_dataset, root)
    assert ds.format == "yolo"
    assert len(ds) == 65 and ds.num_boxes == 2593
    assert ds.class_names == ("car", "truck", "bus", "minibus", "cyclist")
    for r in ds:
        assert np.all(r.boxes[:, 2] > r.boxes[:, 0]) and np.all(r.boxes[:, 3] > r.boxes[:, 1])
        assert np.all(r.boxes >= 0) and np.all(r.boxes[:, 2] <= r.width)
    train, val = split_ids(ds.image_ids)
    assert (len(train), len(val)) == (52, 13)
    assert split_ids(ds.image_ids) == (train, val)  # fixed
    assert not set(train) & set(val)
    # in the detector's classes: trucks, buses and minibuses are cars, the cyclists dropped
    as_car = load_dataset(root, "yolo", ("car", "person"))
    counts = np.bincount(np.concatenate([r.classes for r in as_car]), minlength=2)
    assert counts.tolist() == [2546 + 25 + 22, 0]


@pytest.mark.realdata
def test_raccoon_voc_counts():
    root = shared_path("detection", "raccoon_voc")
    ds = load_dataset(root)
    assert ds.format == "voc" and len(ds) == 200 and ds.class_names == ("raccoon",)
    first = next(r for r in ds if r.image_id == "raccoon-1.jpg")
    # VOC 1-based inclusive (81, 88, 522, 408) -> continuous (80, 87, 522, 408)
    np.testing.assert_allclose(first.boxes, [[80, 87, 522, 408]])
    assert (first.width, first.height) == (650, 417)


# ------------------------------------------------------------------------------ VOC


def test_voc_reader_with_bad_entries(tmp_path):
    (tmp_path / "Annotations").mkdir()
    img_dir = tmp_path / "JPEGImages"
    img_dir.mkdir()
    _image(img_dir / "a.jpg", boxes=[(10, 10, 30, 30)])
    _image(img_dir / "b.jpg")
    _image(img_dir / "neg.jpg")  # no annotation: a negative
    (img_dir / "corrupt.jpg").write_bytes(b"not an image at all")
    _image(img_dir / "badxml.jpg")
    ann = tmp_path / "Annotations"
    ann.joinpath("a.xml").write_text(_voc_xml("a.jpg", [
        ("dog", (11, 11, 30, 30), 0),
        ("cat", (50, 40, 80, 60), 1),  # sticks out: clipped to (49, 39, 64, 48)
        ("dog", ("x", 1, 5, 5), 0),  # malformed
        ("dog", (200, 200, 220, 220), 0),  # wholly outside: dropped
    ]))
    ann.joinpath("b.xml").write_text(_voc_xml("b.jpg", []))
    ann.joinpath("corrupt.xml").write_text(_voc_xml("corrupt.jpg", [("dog", (1, 1, 5, 5), 0)]))
    ann.joinpath("badxml.xml").write_text("<annotation><object>")
    ds, warns = _caught(read_voc, tmp_path)
    assert len(warns) == 1
    msg = str(warns[0].message)
    for word in ("corrupt.jpg", "badxml.xml", "a.xml object 3", "a.jpg box", "clipped 1"):
        assert word in msg, word
    assert ds.class_names == ("cat", "dog")
    assert sorted(ds.image_ids) == ["a.jpg", "b.jpg", "neg.jpg"]
    a = next(r for r in ds if r.image_id == "a.jpg")
    np.testing.assert_allclose(a.boxes, [[10, 10, 30, 30], [49, 39, 64, 48]])
    assert a.classes.tolist() == [1, 0] and a.difficult.tolist() == [False, True]
    assert len(next(r for r in ds if r.image_id == "neg.jpg")) == 0
    assert detect_format(tmp_path) == "voc"
    # a given class list: unknown names are skipped (and listed)
    ds2, warns2 = _caught(read_voc, tmp_path, ["dog"])
    assert ds2.class_names == ("dog",) and "'cat' not in the list" in str(warns2[0].message)


# ------------------------------------------------------------------------------ YOLO


def test_yolo_reader_with_bad_entries(tmp_path):
    _image(tmp_path / "a.png", boxes=[(16, 12, 48, 36)])
    (tmp_path / "a.txt").write_text(
        "0 0.5 0.5 0.5 0.5\n"  # fine: (16, 12, 48, 36)
        "1 0.95 0.5 0.2 0.2\n"  # clipped on the right
        "7 0.5 0.5 0.1 0.1\n"  # class out of range
        "0 0.5 0.5 -0.1 0.1\n"  # negative width
        "0 0.5 0.5\n"  # too few fields
        "0 nan 0.5 0.1 0.1\n"  # not finite
        "1 1.8 1.8 0.1 0.1\n"  # wholly outside
    )
    _image(tmp_path / "empty.png")
    (tmp_path / "empty.txt").write_text("")
    _image(tmp_path / "nolabel.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 20)
    (tmp_path / "classes.txt").write_text("car\nbus\n")
    ds, warns = _caught(read_yolo, tmp_path)
    assert len(warns) == 1
    msg = str(warns[0].message)
    for word in ("broken.png", "a.txt line 3", "a.txt line 4", "a.txt line 5", "a.txt line 6",
                 "a.png box 3", "clipped 1"):
        assert word in msg, word
    assert ds.class_names == ("car", "bus")
    assert sorted(ds.image_ids) == ["a.png", "empty.png", "nolabel.png"]
    a = next(r for r in ds if r.image_id == "a.png")
    np.testing.assert_allclose(a.boxes, [[16, 12, 48, 36], [54.4, 19.2, 64, 28.8]], atol=1e-4)
    assert detect_format(tmp_path) == "yolo"


def test_yolo_ultralytics_layout(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "labels").mkdir()
    _image(tmp_path / "images" / "x.jpg")
    (tmp_path / "labels" / "x.txt").write_text("0 0.5 0.5 0.25 0.25\n")
    ds = load_dataset(tmp_path, "yolo")
    assert ds.class_names == ("0",) and ds.num_boxes == 1


# ------------------------------------------------------------------------------ COCO


def test_coco_reader(tmp_path):
    (tmp_path / "images").mkdir()
    _image(tmp_path / "images" / "1.jpg")
    _image(tmp_path / "images" / "2.jpg")
    doc = {
        "images": [{"id": 10, "file_name": "1.jpg", "width": 64, "height": 48},
                   {"id": 11, "file_name": "2.jpg", "width": 64, "height": 48}],
        "categories": [{"id": 3, "name": "person"}, {"id": 1, "name": "car"}],
        "annotations": [
            {"id": 1, "image_id": 10, "category_id": 3, "bbox": [5, 5, 10, 20], "iscrowd": 0},
            {"id": 2, "image_id": 10, "category_id": 1, "bbox": [0, 0, 4, 4], "iscrowd": 1},
            {"id": 3, "image_id": 10, "category_id": 9, "bbox": [0, 0, 4, 4]},  # bad category
            {"id": 4, "image_id": 10, "category_id": 1, "bbox": [0, 0, 0, 4]},  # empty
        ],
    }
    (tmp_path / "instances.json").write_text(json.dumps(doc))
    ds, warns = _caught(read_coco, tmp_path)
    assert len(warns) == 1 and "annotation 3" in str(warns[0].message)
    assert ds.class_names == ("car", "person") and ds.category_ids == (1, 3)
    r = next(r for r in ds if r.image_id == "1.jpg")
    np.testing.assert_allclose(r.boxes, [[5, 5, 15, 25], [0, 0, 4, 4]])
    assert r.classes.tolist() == [1, 0] and r.difficult.tolist() == [False, True]
    assert len(next(r for r in ds if r.image_id == "2.jpg")) == 0
    assert detect_format(tmp_path) == "coco"


# ------------------------------------------------------------------------------ simulator


_T_BS = "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n"


def _sim_folder(root, ts, w=64, h=48):
    """A minimal ASL folder as the simulator writes it: cam0 (w x h at 20 Hz) and imu0."""
    mav0 = root / "mav0"
    (mav0 / "cam0" / "data").mkdir(parents=True)
    (mav0 / "cam0" / "sensor.yaml").write_text(
        f"%YAML:1.0\nsensor_type: camera\n{_T_BS}rate_hz: 20\nresolution: [{w}, {h}]\n"
        "camera_model: pinhole\nintrinsics: [50.0, 50.0, 32.0, 24.0]\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")
    (mav0 / "cam0" / "data.csv").write_text(
        "#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in ts))
    for t in ts:
        _image(mav0 / "cam0" / "data" / f"{t}.png", w, h)
    (mav0 / "imu0").mkdir()
    (mav0 / "imu0" / "sensor.yaml").write_text(
        f"%YAML:1.0\nsensor_type: imu\n{_T_BS}rate_hz: 200\n"
        "gyroscope_noise_density: 1.0e-4\ngyroscope_random_walk: 2.0e-5\n"
        "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n")
    imu_t = range(ts[0], ts[-1] + 1, 5_000_000)
    (mav0 / "imu0" / "data.csv").write_text(
        "#timestamp [ns],wx,wy,wz,ax,ay,az\n" + "".join(f"{t},0,0,0,0,0,9.81\n" for t in imu_t))
    return mav0


def test_sim_targets_reader(tmp_path):
    from uavcal_jax.data.targets import TargetLabels, write_target_labels

    ts = [10**18 + i * 50_000_000 for i in range(3)]
    mav0 = _sim_folder(tmp_path, ts)
    labels = TargetLabels(
        t_ns=np.array([ts[0], ts[2]]), camera=np.array(["cam0", "cam0"]),
        track_id=np.array([0, 0]), class_id=np.array([0, 0]),
        box=np.array([[5.0, 6, 20, 30], [10, 10, 70, 20]]), visible_pixels=np.array([9, 9]),
        position=np.zeros((2, 3)), class_names=("target",))
    write_target_labels(mav0 / "target0", labels)
    assert detect_format(tmp_path) == "sim"
    ds, warns = _caught(read_sim_targets, tmp_path)
    assert len(warns) == 1 and "clipped 1" in str(warns[0].message)
    assert len(ds) == 3 and ds.class_names == ("target",)
    np.testing.assert_allclose(ds[0].boxes, [[5, 6, 20, 30]])
    assert len(ds[1]) == 0
    np.testing.assert_allclose(ds[2].boxes, [[10, 10, 64, 20]])  # clipped to width 64


def test_sim_targets_use_the_euroc_rules(tmp_path):
    """Frames go through read_euroc: a listed frame without its image is dropped with the
    EuRoC reader's warning, and timestamps going backwards are a DataError naming the line."""
    from uavcal_jax.data.targets import TargetLabels, write_target_labels

    ts = [10**18 + i * 50_000_000 for i in range(4)]
    mav0 = _sim_folder(tmp_path, ts)
    write_target_labels(mav0 / "target0", TargetLabels(
        t_ns=np.array([ts[1]]), camera=np.array(["cam0"]), track_id=np.array([0]),
        class_id=np.array([0]), box=np.array([[5.0, 6, 20, 30]]),
        visible_pixels=np.array([9]), position=np.zeros((1, 3)), class_names=("target",)))
    (mav0 / "cam0" / "data" / f"{ts[3]}.png").unlink()
    ds, warns = _caught(read_sim_targets, tmp_path)
    assert len(ds) == 3 and [len(r) for r in ds] == [0, 1, 0]
    assert len(warns) == 1 and "missing" in str(warns[0].message)
    assert ds[1].image_id == f"cam0/{ts[1]}.png"
    every_other, _ = _caught(read_sim_targets, tmp_path, stride=2, check_images=False)
    assert [r.image_id for r in every_other] == [f"cam0/{ts[0]}.png", f"cam0/{ts[2]}.png"]
    csv = mav0 / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join([lines[0], lines[2], lines[1], *lines[3:4]]) + "\n")
    with pytest.raises(DataError, match="data.csv") as err:
        read_sim_targets(tmp_path)
    assert err.value.row == 3


# ------------------------------------------------------------------------------ errors


def test_errors_name_the_path(tmp_path):
    with pytest.raises(DataError, match="no such data folder"):
        load_dataset(tmp_path / "missing")
    with pytest.raises(DataError, match="cannot tell"):
        load_dataset(tmp_path)
    (tmp_path / "classes.txt").write_text("a\n")
    with pytest.raises(DataError, match="no images"):
        load_dataset(tmp_path)
    with pytest.raises(DataError, match="unknown data set format"):
        load_dataset(tmp_path, "kitti")


def test_split_is_fixed_and_disjoint():
    ids = [f"img{i:03d}.jpg" for i in range(50)]
    train, val = split_ids(ids)
    assert len(val) == 10 and len(train) == 40 and not set(train) & set(val)
    assert split_ids(list(reversed(ids))) == (train, val)
    assert split_ids(ids, seed=1) != (train, val)


# ------------------------------------------------------------------------------ augment


def test_letterbox_round_trip():
    img = np.zeros((100, 300, 3), np.uint8)
    out, r, pad = letterbox(img, (96, 128))
    assert out.shape == (96, 128, 3)
    boxes = np.array([[10.0, 20, 50, 80], [0, 0, 300, 100]])
    there = scale_boxes(boxes, r, pad)
    assert there[1, 0] == pytest.approx(pad[0]) and there[1, 2] == pytest.approx(128, abs=0.5)
    np.testing.assert_allclose(unletterbox_boxes(there, r, pad), boxes, atol=1e-3)


def test_affine_flip_and_mosaic_keep_boxes_on_objects():
    rng = np.random.default_rng(0)
    img = np.zeros((96, 128, 3), np.uint8)
    img[30:60, 40:80] = 255
    boxes = np.array([[40.0, 30, 80, 60]], np.float32)
    out, b, c = random_affine(img, boxes, np.array([0]), rng, (96, 128), scale=0.3,
                              translate=0.1)
    assert len(b) == 1
    x0, y0, x1, y1 = np.round(b[0]).astype(int)
    assert out[(y0 + y1) // 2, (x0 + x1) // 2].min() > 200  # box centre is on the object
    flipped, fb = hflip(img, boxes)
    np.testing.assert_allclose(fb, [[48, 30, 88, 60]])
    assert flipped[45, 60].min() == 255 and flipped[45, 100].max() == 0
    canvas, mb, mc = mosaic4([(img, boxes, np.array([0]))] * 4, (96, 128), rng)
    assert canvas.shape == (192, 256, 3) and len(mb) >= 1
    for x0, y0, x1, y1 in mb.astype(int):
        assert canvas[(y0 + y1) // 2, (x0 + x1) // 2].min() == 255


def test_random_crop_keeps_boxes_on_objects_at_every_zoom_and_quarter_turn():
    img = np.zeros((400, 1200, 3), np.uint8)
    boxes = np.array([[100.0, 50, 140, 70], [600, 300, 680, 340], [1000, 200, 1030, 260]],
                     np.float32)
    for x0, y0, x1, y1 in boxes.astype(int):
        img[y0:y1, x0:x1] = 255
    kept = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        out, b, _ = random_crop(img, boxes, np.arange(3), rng, (160, 192), scale=(0.3, 2.5),
                                rot90=0.5, on_object=0.8, min_area_ratio=0.6)
        assert out.shape == (160, 192, 3)
        for x0, y0, x1, y1 in b:  # each kept box is the object's bounding box
            inside = out[int(np.ceil(y0)):int(y1), int(np.ceil(x0)):int(x1)]
            assert inside.size and inside.mean() > 150
            ys, xs = np.nonzero(out[..., 0] > 127)
            near = (xs >= x0 - 3) & (xs <= x1 + 3) & (ys >= y0 - 3) & (ys <= y1 + 3)
            assert xs[near].min() >= x0 - 2 and xs[near].max() <= x1 + 1
            kept += 1
    assert kept >= 30


def test_yolo_classes_by_name_with_aliases(tmp_path):
    (tmp_path / "classes.txt").write_text("Person\nbus\ncar\nbicycle\n")
    _image(tmp_path / "a.png", 64, 48, [(5, 5, 20, 20)])
    (tmp_path / "a.txt").write_text("0 0.2 0.2 0.1 0.1\n1 0.5 0.5 0.2 0.2\n"
                                    "2 0.7 0.7 0.1 0.1\n3 0.4 0.4 0.1 0.1\n")
    ds = load_dataset(tmp_path, "yolo", ("car", "person"))
    assert ds.class_names == ("car", "person")
    assert ds.records[0].classes.tolist() == [1, 0, 0]  # Person, bus -> car, car; no bicycle
    assert class_index("minibus", ("car", "person")) == 0
    assert class_index("truck", ("truck", "car")) == 0  # a model's own class comes first


# ------------------------------------------------------------------------------ loader


def _tiny_yolo_set(root, n=6):
    rng = np.random.default_rng(1)
    (root / "classes.txt").write_text("box\nbar\n")
    for i in range(n):
        w, h = 120, 90
        x0, y0 = rng.integers(5, 60), rng.integers(5, 40)
        bw, bh = rng.integers(15, 50), rng.integers(15, 40)
        _image(root / f"{i}.png", w, h, [(x0, y0, x0 + bw, y0 + bh)])
        cx, cy = (x0 + bw / 2) / w, (y0 + bh / 2) / h
        (root / f"{i}.txt").write_text(f"{i % 2} {cx} {cy} {bw / w} {bh / h}\n")


def test_loader_shapes_determinism_and_targets(tmp_path):
    _tiny_yolo_set(tmp_path)
    ds = load_dataset(tmp_path)
    plain = DetectionLoader(ds, (64, 96), 4)
    assert len(plain) == 2 and plain.max_targets == 8
    batches = list(plain.epoch(0))
    b = batches[0]
    assert b.images.shape == (4, 64, 96, 3) and b.images.dtype == np.float32
    assert b.targets.shape == (4, 8, 6) and b.images.min() >= 0 and b.images.max() <= 1
    assert batches[1].indices.tolist() == [4, 5, -1, -1]  # padded last batch
    # targets match the records after letterboxing
    rec = ds[int(b.indices[0])]
    there = scale_boxes(rec.boxes, float(b.ratios[0]), tuple(b.pads[0]))[0]
    t = b.targets[0, 0]
    assert t[0] == 1 and t[1] == rec.classes[0]
    np.testing.assert_allclose(t[2:], [(there[0] + there[2]) / 2, (there[1] + there[3]) / 2,
                                       there[2] - there[0], there[3] - there[1]], atol=1e-4)
    # the object really is under its target box
    cx, cy = int(t[2]), int(t[3])
    assert b.images[0, cy, cx, 1] > 0.6  # green (200) in RGB order
    assert b.images[0, cy, cx, 0] < 0.2  # the red channel is 30 (BGR 220, 200, 30 on disk)
    # augmented, shuffled: deterministic from (seed, epoch), different across epochs
    aug = DetectionLoader(ds, (64, 96), 4, augment=AugmentConfig(mosaic=0.5), shuffle=True,
                          seed=3, drop_last=True)
    e0 = list(aug.epoch(0))
    e0b = list(DetectionLoader(ds, (64, 96), 4, augment=AugmentConfig(mosaic=0.5),
                               shuffle=True, seed=3, drop_last=True, workers=1).epoch(0))
    e1 = list(aug.epoch(1))
    assert len(e0) == 1
    np.testing.assert_array_equal(e0[0].images, e0b[0].images)
    np.testing.assert_array_equal(e0[0].targets, e0b[0].targets)
    assert not np.array_equal(e0[0].images, e1[0].images)
    assert aug.max_targets == 8  # 1 box x 4 (mosaic) -> 8
