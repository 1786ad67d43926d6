"""The detections the run's VIO front end waits on (``uavcal_jax.pipeline.run.DetectionBoard``):
a frame's boxes once the detector thread has published them, the last detected frame's when the
detector runs every k-th frame, and no wait for ever when the detector stops."""

from __future__ import annotations

import threading
import time

import numpy as np

from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.pipeline.run import DetectionBoard


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
