"""pipeline.tracker: the online target stage over frames with boxes, frames without, frames
the detector skipped and a target re-acquired long after its last box; without a pose the
follow set-point waits, with one it starts at the pose, held while nothing is known."""

import dataclasses

import numpy as np

from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.pipeline.tracker import TargetTracker
from uavcal_jax.pipeline.tracker_locate import FrameSensors, Localizer
from uavcal_jax.sim.config import SimConfig, camera_calibrations
from uavcal_jax.track import UNSEEN


def test_frames_without_boxes_and_a_target_reacquired_long_after():
    config = RunConfig()
    config = dataclasses.replace(config, associate=dataclasses.replace(
        config.associate, reacquire=True))
    left = camera_calibrations(SimConfig(resolution=(188, 120)))["cam0"]
    tracker = TargetTracker(config, 0, Localizer(config, "off", left, reason="off: test"))
    car = ImageDetections(np.array([[40.0, 40.0, 90.0, 80.0]]), np.ones(1), np.zeros(1, int))
    elsewhere = ImageDetections(np.array([[120.0, 20.0, 170.0, 60.0]]), np.ones(1),
                                np.zeros(1, int))
    none = ImageDetections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int))
    frames = [car] * 3 + [None] + [none] * 30 + [elsewhere] * 2  # long past every window
    T = np.eye(4)
    out = [tracker.step(0.05 * k, det, None if k < 2 else T, FrameSensors())
           for k, det in enumerate(frames)]
    assert [e.track_id for e in out[:3]] == [0, 0, 0]
    assert out[3].track_ids is None and out[3].track_id is None
    assert all(e.track_id is None for e in out[4:34])
    assert [e.track_id for e in out[34:]] == [1, 1]  # a new track, re-acquired
    np.testing.assert_array_equal(out[35].box, elsewhere.boxes[0])
    assert out[0].located.reason == "off: test" and not out[0].located.located
    assert all(int(e.filtered.status) == UNSEEN for e in out)
    assert out[0].setpoint is None and out[1].setpoint is None  # no pose yet
    for e in out[2:]:  # started at the first pose, held: nothing known
        np.testing.assert_array_equal(e.setpoint.position, np.zeros(3))


class _CountingLocalizer(Localizer):
    """The "off" localizer, counting the boxes it is asked to locate."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.asked = []

    def locate(self, box, T_WB, sensors):
        self.asked.append(tuple(np.asarray(box, float)))
        return super().locate(box, T_WB, sensors)


def test_a_doubtful_box_that_continues_no_track_is_never_located():
    """ByteTrack's second round: a box under the track-start score can only continue a
    track; one that overlaps none (clutter scoring 0.3-0.59, as the real EuRoC room's
    mattress) is dropped before the same-target checks locate it."""
    config = RunConfig()
    left = camera_calibrations(SimConfig(resolution=(188, 120)))["cam0"]
    localizer = _CountingLocalizer(config, "off", left, reason="off: test")
    tracker = TargetTracker(config, 0, localizer)
    start = config.detect.score_threshold
    car = np.array([40.0, 40.0, 90.0, 80.0])
    part = np.array([42.0, 42.0, 60.0, 60.0])  # inside the car's box
    clutter, clutter_part = np.array([120.0, 20.0, 170.0, 60.0]), np.array([122, 22, 140, 40.])
    doubtful = start - 0.1
    frames = [ImageDetections(np.stack([car, part]), np.array([0.9, 0.9]), np.zeros(2, int)),
              ImageDetections(np.stack([car + 2, part + 2, clutter, clutter_part]),
                              np.array([doubtful, doubtful, doubtful, doubtful]),
                              np.zeros(4, int))]
    out = [tracker.step(0.05 * k, det, np.eye(4), FrameSensors())
           for k, det in enumerate(frames)]
    assert out[1].track_id == 0  # the doubtful car box continued its track
    np.testing.assert_array_equal(out[1].track_ids, [0, -1, -1, -1])
    asked = set(localizer.asked)
    assert tuple(clutter) not in asked and tuple(clutter_part) not in asked
    assert tuple(car + 2) in asked  # its part was checked against it


def test_a_loose_doubtful_box_still_marks_the_boxes_inside_it_as_parts():
    """A track that followed a part of a car (a box inside the car's) is not continued by the
    part while a larger doubtful box of the whole car, which continues no track, surrounds
    it: the part box is dropped as the whole's part (located as one target with it), as it
    was before doubtful boxes that continue no track were dropped unlocated."""
    config = RunConfig()
    left = camera_calibrations(SimConfig(resolution=(188, 120)))["cam0"]
    tracker = TargetTracker(config, 0, Localizer(config, "off", left, reason="off: test"))
    doubtful = config.detect.score_threshold - 0.1
    part = np.array([60.0, 50.0, 80.0, 70.0])
    whole = np.array([20.0, 20.0, 120.0, 100.0])  # IoU with the part's track under min_iou
    frames = [ImageDetections(part[None], np.array([0.9]), np.zeros(1, int)),
              ImageDetections(np.stack([whole, part + 1]), np.array([doubtful, doubtful]),
                              np.zeros(2, int))]
    out = [tracker.step(0.05 * k, det, np.eye(4), FrameSensors())
           for k, det in enumerate(frames)]
    assert out[0].track_id == 0
    np.testing.assert_array_equal(out[1].track_ids, [-1, -1])
    assert out[1].track_id is None
