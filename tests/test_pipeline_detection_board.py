"""The detections the run's VIO front end waits on (``uavcal_jax.pipeline.run.DetectionBoard``):
a frame's boxes once the detector thread has published them, the last detected frame's when the
detector runs every k-th frame, no wait for ever when the detector stops, and the mask's lower
score threshold."""

from __future__ import annotations

import dataclasses
import threading
import time
from types import SimpleNamespace

import numpy as np

from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.pipeline import run as run_module
from uavcal_jax.pipeline.run import DetectionBoard
from uavcal_jax.pipeline.run_config import DetectStageConfig, RunConfig


def _found(k: int) -> ImageDetections:
    return ImageDetections(np.array([[k, 0.0, k + 10.0, 5.0]]), np.array([0.9]), np.array([0]))


def test_boxes_wait_for_the_detector_and_take_the_last_detected_frame():
    board = DetectionBoard(6, every=2)
    got = {}

    def front_end():
        got[3] = board.boxes(3)  # frame 2's (every 2nd frame detected)
        got[4] = board.boxes(4)

    reader = threading.Thread(target=front_end)
    reader.start()
    time.sleep(0.05)
    assert not got  # nothing published yet: the front end waits
    for k in (0, 2, 4):
        board.publish(k, _found(k))
    reader.join(timeout=5)
    assert not reader.is_alive()
    np.testing.assert_array_equal(got[3], _found(2).boxes)
    np.testing.assert_array_equal(got[4], _found(4).boxes)
    assert board.frames[1] is None and board.frames[2] is not None


def test_a_stopped_detector_releases_the_front_end_with_no_boxes():
    board = DetectionBoard(4, every=1)
    board.publish(0, _found(0))
    board.finish()  # e.g. the detector raised
    assert board.boxes(3) is None
    np.testing.assert_array_equal(board.boxes(0), _found(0).boxes)


def test_the_vio_mask_takes_doubtful_boxes_the_tracker_does_not(monkeypatch):
    """A box scoring between ``detect.mask_score_threshold`` and the tracker's lowest score
    (``detect.continue_score_threshold``) is left out of the VIO's front end but is not a
    detection of the run."""
    sure, doubtful = (np.array([[10.0, 10.0, 50.0, 40.0]]), np.array([[100.0, 20.0, 140.0, 60.0]]))

    class Detector:
        needs_images = False

        def __call__(self, images, t_ns):
            return [ImageDetections(np.concatenate([sure, doubtful]), np.array([0.9, 0.4]),
                                    np.array([0, 0]))]

    camera = type("Camera", (), {"__len__": lambda self: 3,
                                 "t_ns": np.arange(3) * 50_000_000})()
    sequence = SimpleNamespace(camera=lambda name: camera)
    masked = {}

    def fake_vio(sequence, config, offset, show_progress, exclude_boxes):
        for k in range(3):
            masked[k] = exclude_boxes(k)
        return "vio"

    monkeypatch.setattr(run_module, "run_vio", fake_vio)
    config = RunConfig(detect=DetectStageConfig(score_threshold=0.6, continue_score_threshold=0.5,
                                                mask_score_threshold=0.25))
    vio, detections, _, frames = run_module._vio_and_detect(sequence, config, np.zeros(6),
                                                             Detector(), False)
    assert vio == "vio" and frames == 3
    for k in range(3):
        np.testing.assert_array_equal(masked[k], np.concatenate([sure, doubtful]))
        np.testing.assert_array_equal(detections[k].boxes, sure)
    # without the mask, the detector's threshold is the tracker's lowest
    assert dataclasses.replace(config.detect, mask_vio=False).detector_threshold() == 0.5
    assert config.detect.detector_threshold() == 0.25
