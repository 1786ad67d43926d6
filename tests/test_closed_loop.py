"""The closed loop (:func:`uavcal_jax.pipeline.closed_loop.fly_closed_loop`) against the
simulator's ground truth: the drone flies the online tracker's set-points from the true pose,
with the renderer's own boxes, at a low resolution and frame rate (CI-small)."""

import dataclasses

import numpy as np
import pytest

from uavcal_jax.pipeline.closed_loop import ClosedLoopConfig, fly_closed_loop
from uavcal_jax.pipeline.run_config import RunConfig
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.ground_target import GroundPath

FOLLOW = RunConfig().follow
SIM = SimConfig(duration=6.0, resolution=(188, 120), camera_pitch_deg=30.0, blur_samples=1,
                camera_rate_hz=10.0)


def _fly(**changes):
    config = dataclasses.replace(ClosedLoopConfig(pose="true", sim=SIM), **changes)
    return fly_closed_loop(config, None, "labels")


@pytest.fixture(scope="module")
def static_flight():
    """A car that never starts; the drone starts 2 m too far back, 1 m aside, 1 m high."""
    return _fly(path=GroundPath(wait_s=100.0), start_offset=(-2.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def moving_flight():
    """The scripted car: it starts after 1 s and drives its straight leg at 1.5 m/s."""
    return _fly(path=GroundPath(wait_s=1.0))


def test_static_target_is_reached_and_held(static_flight):
    r = static_flight
    horizontal = np.linalg.norm(r.target[:, :2] - r.drone[:, :2], axis=1)
    height = r.drone[:, 2] - r.target[:, 2]
    start_error = abs(horizontal[0] - FOLLOW.distance)
    assert start_error > 1.5  # the drone starts off the stand-off
    end = r.t >= r.t[-1] - 1.0  # the last second: reached, and held there
    assert np.all(np.abs(horizontal[end] - FOLLOW.distance) < 0.3)
    assert np.all(np.abs(height[end] - FOLLOW.height) < 0.3)
    assert np.all(r.in_view)
    # the filtered car against the truth (at 188x120 the box model's centre is off by
    # about 0.35 m here: the car's heading is the box shape's alone)
    assert np.nanmax(np.linalg.norm(r.filtered[end] - r.target[end], axis=1)) < 0.5


def test_moving_target_stays_in_view_at_the_follow_distance(moving_flight):
    r = moving_flight
    m = r.metrics
    assert m["evaluated_frames"] >= 40
    assert np.linalg.norm(r.target[-1] - r.target[0]) > 5.0  # the car did drive
    assert m["in_view_fraction"] == 1.0
    assert m["measured_fraction"] > 0.95
    assert m["distance_error_m"]["max"] < 1.0
    assert m["distance_error_m"]["mean"] < 0.5
    assert m["height_error_m"]["max"] < 0.5
    assert m["localisation_rmse_m"]["filtered"]["rmse"] < 0.5
