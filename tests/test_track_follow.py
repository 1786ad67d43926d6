"""track.follow and track.associate: the set-point law (exact stand-off, height and yaw on a
static target; equivariance to rotating and translating the world; yaw wrapping the short way
at +-pi; rate limits; a moving and a lost target), and detection association (ids kept through
a crossing and a missed frames; a part of a larger box dropped; a box the localisation
refuses not matched). The choice of the followed target: test_track_chain."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from track_folds import assign_track_ids, follow_setpoints

from uavcal_jax.track import associate as A
from uavcal_jax.track import follow as W

DT = 0.05
CFG = W.FollowConfig(distance=4.0, height=2.0, max_speed=3.0, max_yaw_rate=1.0,
                     min_yaw_distance=0.5)


@functools.partial(jax.jit, static_argnames=("config", "n"))
def _closed_loop(targets, known, start_p, start_yaw, config=CFG, n=200):
    """The drone flies its set-points exactly: the actual position of frame k is the
    set-point of frame k - 1. targets (n, 3) -> positions (n, 3), yaws (n,)."""

    def step(prev, frame):
        target, k = frame
        nxt = W.follow_step(prev, target, k, prev.position, DT, config)
        return nxt, nxt

    _, out = jax.lax.scan(step, W.Setpoint(start_p, start_yaw), (targets, known))
    return out


def _bearing(frm, to):
    return np.arctan2(to[1] - frm[1], to[0] - frm[0])


def _angle_diff(a, b):
    return np.asarray(W.wrap_angle(np.asarray(a) - np.asarray(b)))


def test_static_target_gives_exact_distance_height_and_yaw():
    target = np.array([3.0, -1.0, 0.8])
    n = 200
    out = _closed_loop(jnp.broadcast_to(target, (n, 3)), jnp.ones(n, bool),
                       jnp.array([-6.0, 5.0, 1.0]), jnp.asarray(0.3))
    p, yaw = np.asarray(out.position[-1]), float(out.yaw[-1])
    assert abs(np.linalg.norm(p[:2] - target[:2]) - CFG.distance) < 1e-5
    assert abs(p[2] - (target[2] + CFG.height)) < 1e-5
    assert abs(_angle_diff(yaw, _bearing(p, target))) < 1e-5
    # the stand-off lies on the line from the target to where the drone started
    start_dir = np.array([-6.0, 5.0]) - target[:2]
    assert abs(_angle_diff(_bearing(target, p), np.arctan2(start_dir[1], start_dir[0]))) < 1e-5
    # rate limits: no step faster than max_speed, no turn faster than max_yaw_rate
    steps = np.linalg.norm(np.diff(np.asarray(out.position), axis=0), axis=1)
    assert steps.max() <= CFG.max_speed * DT * (1 + 1e-5)
    turns = np.abs(_angle_diff(np.asarray(out.yaw[1:]), np.asarray(out.yaw[:-1])))
    assert turns.max() <= CFG.max_yaw_rate * DT * (1 + 1e-5)


def test_one_step_is_the_desired_position_when_within_reach():
    target, drone = np.array([0.0, 0.0, 1.0]), np.array([3.0, 4.0, 3.0])  # 5 m away
    prev = W.Setpoint(jnp.asarray(drone), jnp.asarray(0.0))
    config = W.FollowConfig(distance=4.0, height=2.0, max_speed=10.0)
    sp = W.follow_step(prev, target, True, drone, 1.0, config)
    np.testing.assert_allclose(np.asarray(sp.position), [0.8 * 3.0, 0.8 * 4.0, 3.0], atol=1e-6)
    # yaw faces the target from the drone's actual position, limited to 1 rad/s for 1 s
    want = _bearing(drone, target)
    assert abs(float(sp.yaw) - np.clip(want, -1.0, 1.0)) < 1e-6


def test_equivariant_to_rotating_and_translating_the_world():
    rng = np.random.default_rng(0)
    n = 120
    times = np.arange(n) * DT
    targets = np.array([1.0, 2.0, 0.5]) + np.stack(
        [np.sin(times), 0.5 * times, 0.1 * np.cos(2 * times)], axis=1)
    drones = np.array([-3.0, 0.0, 2.0]) + 0.3 * rng.standard_normal((n, 3))
    known = np.ones(n, bool)
    known[40:45] = False
    start = W.Setpoint(drones[0], 0.2)
    base = follow_setpoints(times, targets, known, drones, start, CFG)

    theta, shift = 2.3, np.array([10.0, -4.0, 1.5])
    c, s = np.cos(theta), np.sin(theta)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = follow_setpoints(times, targets @ Rz.T + shift, known, drones @ Rz.T + shift,
                               W.Setpoint(drones[0] @ Rz.T + shift, 0.2 + theta), CFG)
    np.testing.assert_allclose(np.asarray(moved.position),
                               np.asarray(base.position) @ Rz.T + shift, atol=1e-4)
    np.testing.assert_allclose(_angle_diff(moved.yaw, np.asarray(base.yaw) + theta), 0.0,
                               atol=1e-4)


def test_yaw_wraps_the_short_way_at_pi():
    # facing yaw 3.0 (near +pi); the target is at bearing -3.0 (just past -pi): 0.28 rad away
    # the short way through pi, 6.0 rad the long way through 0
    drone = np.array([0.0, 0.0, 2.0])
    target = drone + 4.0 * np.array([np.cos(-3.0), np.sin(-3.0), 0.0])
    n = 20
    out = follow_setpoints(np.arange(n) * DT, np.broadcast_to(target, (n, 3)),
                             np.ones(n, bool), np.broadcast_to(drone, (n, 3)),
                             W.Setpoint(drone, 3.0), CFG)
    yaw = np.asarray(out.yaw)
    assert np.all((yaw >= -np.pi) & (yaw < np.pi))
    assert np.all(np.abs(yaw) > 2.9)  # never swings through 0
    turns = _angle_diff(yaw, np.concatenate([[3.0], yaw[:-1]]))
    assert np.all(turns >= 0.0) and turns.max() <= CFG.max_yaw_rate * DT * (1 + 1e-5)
    assert abs(yaw[-1] - (-3.0)) < 1e-5  # reached after 0.28 / (1 rad/s) = 6 frames
    assert yaw[0] > 0 and yaw[-1] < 0  # crossed pi
    assert float(W.wrap_angle(np.pi)) == pytest.approx(-np.pi)


def test_yaw_holds_near_the_target_and_setpoints_hold_without_one():
    drone = np.array([1.0, 1.0, 3.0])
    above = np.array([1.2, 1.1, 0.0])  # 0.22 m horizontally: below min_yaw_distance
    prev = W.Setpoint(jnp.asarray(drone), jnp.asarray(1.234))
    assert float(W.follow_step(prev, above, True, drone, DT, CFG).yaw) == pytest.approx(1.234)
    unknown = W.follow_step(prev, np.full(3, np.nan), False, drone, DT, CFG)
    np.testing.assert_array_equal(np.asarray(unknown.position), drone)
    assert float(unknown.yaw) == pytest.approx(1.234)


def test_moving_target_is_followed_and_a_lost_one_held():
    n = 200
    t = np.arange(n) * DT
    targets = np.stack([1.0 * t, 0.3 * t, np.zeros(n)], axis=1)  # 1.04 m/s < max_speed
    lost_from = 150
    targets[lost_from:] = targets[lost_from - 1]  # the filter holds its last prediction
    out = _closed_loop(jnp.asarray(targets), jnp.ones(n, bool), jnp.array([-5.0, 0.0, 2.0]),
                       jnp.asarray(0.0))
    p = np.asarray(out.position)
    d = np.linalg.norm(p[:, :2] - targets[:, :2], axis=1)
    np.testing.assert_allclose(d[60:], CFG.distance, atol=1e-4)  # after the approach
    np.testing.assert_allclose(p[60:, 2], CFG.height, atol=1e-4)
    np.testing.assert_allclose(p[-1], p[lost_from + 5], atol=1e-5)  # held at the stand-off
    assert abs(_angle_diff(out.yaw[-1], _bearing(p[-1], targets[-1]))) < 1e-4


# --- association ----------------------------------------------------------------------------


def _crossing(n=21):
    """Two same-class 20x20 boxes crossing head-on (full overlap at frame 10), a third of
    another class; box A missing at frame 5, both missing at the crossing frame 10."""
    boxes, classes, truth = [], [], []
    for k in range(n):
        xa, xb = 10.0 + 10.0 * k, 210.0 - 10.0 * k
        rows, cls, ids = [], [], []
        if k not in (5, 10):
            rows.append([xa, 50.0, xa + 20.0, 70.0]); cls.append(0); ids.append("A")  # noqa: E702
        if k != 10:
            rows.append([xb, 52.0, xb + 20.0, 72.0]); cls.append(0); ids.append("B")  # noqa: E702
        if k >= 3:
            rows.append([100.0, 150.0, 130.0, 190.0]); cls.append(1); ids.append("C")  # noqa: E702
        order = np.random.default_rng(k).permutation(len(rows))  # detections in any order
        boxes.append(np.asarray(rows)[order])
        classes.append(np.asarray(cls)[order])
        truth.append([ids[i] for i in order])
    return boxes, classes, truth


def test_association_keeps_ids_through_a_crossing_and_missed_frames():
    boxes, classes, truth = _crossing()
    ids = assign_track_ids(boxes, classes, A.AssociateConfig(min_iou=0.1, max_missed=3))
    mapping: dict[str, set[int]] = {}
    for frame_ids, frame_truth in zip(ids, truth, strict=True):
        for i, name in zip(frame_ids, frame_truth, strict=True):
            mapping.setdefault(name, set()).add(int(i))
    assert all(len(v) == 1 for v in mapping.values()), mapping  # one id per target
    assert len({next(iter(v)) for v in mapping.values()}) == 3  # three distinct ids


def test_a_part_boxed_beside_its_target_is_dropped_and_other_targets_kept():
    car = [100.0, 100.0, 300.0, 400.0]
    bonnet = [110.0, 90.0, 290.0, 200.0]  # 90 % of it inside the car's box (IoU 0.27)
    neighbour = [280.0, 120.0, 480.0, 420.0]  # another car overlapping the first by 10 %
    person = [150.0, 200.0, 200.0, 330.0]  # inside the car's box, but another class
    boxes = np.array([bonnet, car, neighbour, person])
    classes = np.array([0, 0, 0, 1])
    assert A.box_iou(np.array([bonnet]), np.array([car]))[0, 0] < 0.3  # NMS keeps both
    keep = A.contained_duplicates(boxes, classes, 0.6)
    np.testing.assert_array_equal(keep, [False, True, True, True])
    np.testing.assert_array_equal(A.contained_duplicates(boxes, classes, 0.95), [True] * 4)
    np.testing.assert_array_equal(A.contained_duplicates(boxes, classes, None), [True] * 4)
    assert A.contained_duplicates(np.zeros((0, 4)), np.zeros(0), 0.6).shape == (0,)
    with pytest.raises(ValueError, match="merge_contained"):
        A.AssociateConfig(merge_contained=0.0)


def test_box_iou_against_hand_values():
    iou = A.box_iou(np.array([[0.0, 0.0, 10.0, 10.0]]),
                    np.array([[5.0, 0.0, 15.0, 10.0], [20.0, 20.0, 30.0, 30.0],
                              [0.0, 0.0, 10.0, 10.0]]))
    np.testing.assert_allclose(iou, [[50.0 / 150.0, 0.0, 1.0]])


def test_a_target_seen_past_another_inside_its_box_is_kept():
    """A far car's box inside a near car's is a part only if the two may be one target."""
    near, far = [150.0, 100.0, 550.0, 480.0], [270.0, 180.0, 520.0, 350.0]
    boxes, classes = np.array([near, far]), np.array([0, 0])
    asked = []

    def apart(i, j):
        asked.append((i, j))
        return False

    np.testing.assert_array_equal(A.contained_duplicates(boxes, classes, 0.6, apart),
                                  [True, True])
    assert asked == [(0, 1)]  # the larger box first, asked about the one inside it
    np.testing.assert_array_equal(
        A.contained_duplicates(boxes, classes, 0.6, lambda i, j: True), [True, False])


def test_association_does_not_match_a_box_the_localisation_refuses():
    """Frame 2's box overlaps the track's, but the callback says it is located elsewhere:
    it starts a new track."""
    boxes = [np.array([[100.0, 100.0, 300.0, 300.0]]) + k for k in range(4)]
    classes = [np.zeros(1, np.int64)] * 4
    assert [int(i[0]) for i in assign_track_ids(boxes, classes)] == [0, 0, 0, 0]
    jump = 2  # the first frame of the other target

    def same(k_a, i_a, k_b, i_b):
        return (k_a < jump) == (k_b < jump)

    ids = assign_track_ids(boxes, classes, A.AssociateConfig(), same)
    assert [int(i[0]) for i in ids] == [0, 0, 1, 1]


