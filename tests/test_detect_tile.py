"""Sliced inference (``detect.tile``) against a stub network whose boxes are known: it boxes
every bright blob of its input exactly, so the merged boxes must be the blobs' own boxes in the
image's pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uavcal_jax.detect.predict import ImageDetections, detect_images
from uavcal_jax.detect.tile import (
    TileConfig,
    detect,
    detect_tiled,
    merge_detections,
    needs_slicing,
    tile_origins,
    tile_windows,
)

TILE = (96, 128)  # the stub network's input (H, W)
MAX_DET = 16


def stub_predict(images):
    """A network that boxes each bright connected blob of each input image (pixel edges),
    class 1 for a white blob and 0 for a red one, score 0.9, or 0.3 for a blob touching the
    input's border (cut by it, as a network scores a cut object lower)."""
    B, H, W, _ = images.shape
    boxes = np.zeros((B, MAX_DET, 4), np.float32)
    scores = np.zeros((B, MAX_DET), np.float32)
    classes = np.zeros((B, MAX_DET), np.int32)
    valid = np.zeros((B, MAX_DET), bool)
    for b in range(B):
        mask = (np.asarray(images[b, :, :, 0]) > 0.7).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=4)
        for k, (x, y, w, h, _) in enumerate(stats[1:n][:MAX_DET]):
            boxes[b, k] = (x, y, x + w, y + h)
            cut = x == 0 or y == 0 or x + w == W or y + h == H
            scores[b, k] = 0.3 if cut else 0.9
            ys, xs = np.nonzero(labels == k + 1)
            classes[b, k] = int(np.asarray(images[b, ys[0], xs[0], 2]) > 0.5)
            valid[b, k] = True
    return {"boxes": boxes, "scores": scores, "classes": classes, "valid": valid}


def scene(size=(300, 500), squares=(), big=None):
    """A dark image with ``squares`` ((x0, y0, side, white)) and a ``big`` white box (x0, y0,
    x1, y1); returns the image and the true boxes (x0, y0, x1, y1), classes."""
    image = np.full((*size, 3), 20, np.uint8)
    boxes, classes = [], []
    for x0, y0, side, white in squares:
        image[y0:y0 + side, x0:x0 + side] = (255, 255, 255) if white else (255, 0, 0)
        boxes.append((x0, y0, x0 + side, y0 + side))
        classes.append(int(white))
    if big is not None:
        x0, y0, x1, y1 = big
        image[y0:y1, x0:x1] = 255
    return image, np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(classes)


# small squares straddling window borders (a 300x500 image at overlap 0.3 has windows from
# x 0/74/149/223/298/372 and y 0/68/136/204), and two of the two classes side by side
SQUARES = ((110, 60, 24, True), (240, 130, 24, False), (20, 20, 24, True),
           (370, 200, 24, True), (400, 250, 20, False), (424, 250, 20, True))


def test_windows_cover_the_image_as_sahi_counts_them():
    assert tile_origins(480, 256, 0.2).tolist() == [0, 112, 224]  # SAHI: 3 rows
    assert tile_origins(640, 384, 0.2).tolist() == [0, 256]
    assert tile_origins(200, 256, 0.2).tolist() == [0]
    assert tile_origins(500, 128, 0.3).tolist() == [0, 74, 149, 223, 298, 372]  # SAHI: 6
    windows = tile_windows((300, 500), TILE, 0.3)
    assert windows.shape == (24, 4)
    assert (windows[:, 2] - windows[:, 0] == 128).all() and (windows[:, 3] - windows[:, 1]
                                                            == 96).all()
    assert windows[:, 2].max() == 500 and windows[:, 3].max() == 300
    # every neighbour overlaps by at least int(0.3 * side)
    assert np.diff(np.unique(windows[:, 0])).max() <= 128 - int(0.3 * 128)
    assert tile_windows((50, 60), TILE, 0.2).tolist() == [[0, 0, 60, 50]]


def test_merge_is_classwise_greedy_nms():
    det = ImageDetections(np.array([[0, 0, 10, 10], [2, 2, 6, 6], [0, 0, 10, 10],
                                    [20, 0, 30, 10], [21, 0, 31, 10]], float),
                          np.array([0.9, 0.95, 0.8, 0.7, 0.7]), np.array([0, 0, 1, 0, 0]))
    # IOS: the small box inside the big one of its class is dropped (it scores higher: the
    # big one goes); the other class's box stays; of two equal scores the earlier stays
    ios = merge_detections(det, "ios", 0.5, 10)
    assert ios.boxes.tolist() == [[2, 2, 6, 6], [0, 0, 10, 10], [20, 0, 30, 10]]
    assert ios.classes.tolist() == [0, 1, 0]
    iou = merge_detections(det, "iou", 0.5, 10)  # IoU 0.16: both kept
    assert iou.boxes.tolist() == [[2, 2, 6, 6], [0, 0, 10, 10], [0, 0, 10, 10],
                                  [20, 0, 30, 10]]
    assert len(merge_detections(det, "iou", 0.5, 2).boxes) == 2


def test_tiled_boxes_are_the_objects_in_image_pixels():
    image, truth, classes = scene(squares=SQUARES)
    # without the full-image pass every box is a window's, at full resolution: exact
    (found,) = detect_tiled(stub_predict, [image], TILE, TileConfig(overlap=0.3,
                                                                   full_image=False))
    order = np.lexsort((found.boxes[:, 1], found.boxes[:, 0]))
    expect = np.lexsort((truth[:, 1], truth[:, 0]))
    np.testing.assert_array_equal(found.boxes[order], truth[expect])
    np.testing.assert_array_equal(found.classes[order], classes[expect])
    np.testing.assert_allclose(found.scores, 0.9, rtol=1e-6)
    # the whole letterboxed image (scale 0.256) places them only to a few pixels
    (whole,) = detect_images(stub_predict, [image], TILE)
    order = np.lexsort((whole.boxes[:, 1], whole.boxes[:, 0]))
    assert np.abs(whole.boxes[order] - truth[expect]).max() > 2.0


def test_the_full_image_pass_finds_an_object_larger_than_a_window():
    big = (150, 150, 350, 290)  # 200 x 140 px: no window holds it whole
    image, truth, _ = scene(squares=(SQUARES[0], SQUARES[2], SQUARES[4]), big=big)
    (found,) = detect_tiled(stub_predict, [image], TILE, TileConfig(overlap=0.3))
    # the squares exactly, the big box once (the windows' cut pieces merged into it), to the
    # full-image pass's resolution (0.256 px per image pixel)
    assert len(found.boxes) == len(truth) + 1
    big_rows = [i for i, b in enumerate(found.boxes) if b[2] - b[0] > 100]
    assert len(big_rows) == 1
    np.testing.assert_allclose(found.boxes[big_rows[0]], big, atol=5)
    small = np.delete(found.boxes, big_rows, axis=0)
    np.testing.assert_array_equal(small[np.lexsort((small[:, 1], small[:, 0]))],
                                  truth[np.lexsort((truth[:, 1], truth[:, 0]))])
    # without it the big object comes back only in pieces
    (pieces,) = detect_tiled(stub_predict, [image], TILE, TileConfig(overlap=0.3,
                                                                    full_image=False))
    assert not any(b[2] - b[0] > 190 and b[3] - b[1] > 140 for b in pieces.boxes)


def test_tile_off_is_the_untiled_output():
    image, _, _ = scene(squares=SQUARES)
    small = cv2.resize(image, (120, 80), interpolation=cv2.INTER_NEAREST)
    for images in ([image, small], [small]):
        old = detect_images(stub_predict, images, TILE, 2)
        for new in (detect(stub_predict, images, TILE, 2),
                    # an image that fits one window: the full-image pass only
                    *([detect(stub_predict, images, TILE, 2, TileConfig())]
                      if len(images) == 1 else [])):
            for a, b in zip(old, new, strict=True):
                for field in ImageDetections._fields:
                    np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="overlap"):
        TileConfig(overlap=1.0)
    with pytest.raises(ValueError, match="match_metric"):
        TileConfig(match_metric="giou")


def test_the_run_configures_its_detector_with_tiles():
    from pathlib import Path

    from uavcal_jax.config import apply_overrides
    from uavcal_jax.pipeline.detectors import NetworkDetector
    from uavcal_jax.pipeline.run_config import RunConfig

    assert RunConfig().detect.tile_config() is None  # default off
    config = apply_overrides(RunConfig(), ["detect.tile=true", "detect.tile_overlap=0.3"])
    tile = config.detect.tile_config()
    assert tile == TileConfig(overlap=0.3)
    with pytest.raises(ValueError, match="tile_overlap"):
        apply_overrides(RunConfig(), ["detect.tile_overlap=1.5"])
    image, truth, _ = scene(squares=SQUARES)
    frames = [image, image[::-1].copy()]
    for t in (None, tile):
        detector = NetworkDetector(stub_predict, TILE, ("red", "white"), Path("stub"), tile=t)
        got = detector(frames, [0, 1])
        want = detect(stub_predict, frames, TILE, len(frames), t)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a.boxes, b.boxes)
    assert len(got[0].boxes) == len(truth)


def test_auto_slices_only_images_well_over_the_input():
    image, truth, _ = scene(squares=SQUARES)
    h, w = image.shape[:2]
    auto = TileConfig.of_mode("auto", overlap=0.3, full_image=False)
    assert TileConfig.of_mode("off") is None and TileConfig.of_mode("on") == TileConfig()
    assert needs_slicing((h, w), TILE, auto)  # several times the input: sliced
    (found,) = detect_tiled(stub_predict, [image], TILE, auto)
    assert len(found.boxes) == len(truth)
    # 1.4 times the input's width: letterboxed whole, as without tiles (one batch with the
    # other whole image)
    near = cv2.resize(image, (int(TILE[1] * 1.4), int(TILE[1] * 1.4 * h / w)),
                      interpolation=cv2.INTER_NEAREST)
    assert not needs_slicing(near.shape[:2], TILE, auto)
    assert needs_slicing(near.shape[:2], TILE, TileConfig())
    got = detect_tiled(stub_predict, [near, image, near], TILE, auto)
    (whole,) = detect_images(stub_predict, [near], TILE)
    for field in ImageDetections._fields:
        np.testing.assert_array_equal(getattr(got[0], field), getattr(whole, field))
        np.testing.assert_array_equal(getattr(got[2], field), getattr(whole, field))
    np.testing.assert_array_equal(got[1].boxes, found.boxes)
