"""track.chain: the online choice of the followed target, frame by frame, over the ids of the
online association (track.associate.Associator, which assign_track_ids folds): an identity
break bridged, never onto another target; a target back in view re-acquired only if it could
have got there; a gap at the image edge bridged within stitch_gap; the longest-seen track
chosen and kept while seen; a box the localisation refuses neither matched nor stitched."""

from __future__ import annotations

import numpy as np
from track_folds import assign_track_ids

from uavcal_jax.track import associate as A
from uavcal_jax.track.chain import FollowedChain


def _follow(boxes, config=None, same=None, inside=None, associate_same=None):
    """Per frame, the followed box's index (-1: none) (``same``: the chain's check;
    ``associate_same``: the association's), with the association's ids."""
    config = A.AssociateConfig() if config is None else config
    associator, chain = A.Associator(config), FollowedChain(0, config)
    picks, ids = [], []
    for k, frame in enumerate(boxes):
        frame = np.asarray(frame, np.float64).reshape(-1, 4)
        classes = np.zeros(len(frame), np.int64)
        frame_ids = associator.step(frame, classes, associate_same)
        usable = np.ones(len(frame), bool) if inside is None else inside[k]
        picks.append(chain.step(k, frame_ids, frame, classes, usable, same))
        ids.append(frame_ids)
    return np.array(picks), ids


def test_the_online_association_is_assign_track_ids():
    boxes = [np.array([[10.0 * k, 0.0, 10.0 * k + 50.0, 40.0],
                       [300.0 - 5.0 * k, 0.0, 350.0 - 5.0 * k, 40.0]])[:1 + (k % 3 > 0)]
             for k in range(12)]
    classes = [np.zeros(len(b), np.int64) for b in boxes]
    _, ids = _follow(boxes)
    for a, b in zip(ids, assign_track_ids(boxes, classes), strict=True):
        np.testing.assert_array_equal(a, b)


def test_an_identity_break_is_bridged_and_never_onto_another_target():
    """The followed car F is missed for two frames and comes back with its box jumped back
    (a new track); the chain goes on with it, never with the other car P."""
    boxes, who = [], []
    for k in range(30):
        x = 100.0 + 20 * k - 110.0 * (k >= 14)
        f = [x, 100.0, x + 100.0, 160.0]
        p = [600.0 - 5 * k, 300.0, 700.0 - 5 * k, 380.0]
        frame, names = ([p], ["P"]) if k in (12, 13) else ([f, p], ["F", "P"])
        boxes.append(frame)
        who.append(names)
    pick, ids = _follow(boxes)
    assert len({int(i[0]) for i, n in zip(ids, who, strict=True) if n[0] == "F"}) == 2
    for k, names in enumerate(who):
        assert (names[pick[k]] == "F") if "F" in names else pick[k] == -1, (k, pick[k])
    # stitching off: F is lost; after stitch_gap frames without it the track seen longest
    # so far, P (F's new track has only a few boxes), is chosen
    alone, _ = _follow(boxes, A.AssociateConfig(stitch_iou=1.0, stitch_gap=3))
    assert all(who[k][alone[k]] == "F" for k in range(12))  # the first seen (tied with P)
    assert (alone[12:16] == -1).all()  # waiting for F
    assert all(who[k][alone[k]] == "P" for k in range(16, 30))


def test_a_target_back_in_view_is_reacquired_if_it_could_have_got_there():
    """F leaves the image for 10 frames and comes back elsewhere; a car Q appears 2 frames
    before F. With ``reacquire`` the chain skips Q (the check rejects it) and takes F."""
    boxes, who = [], []
    for k in range(40):
        frame, names = [], []
        if k < 10:
            frame.append([100.0 + 10 * k, 100.0, 200.0 + 10 * k, 160.0]), names.append("F")
        if k >= 20:
            frame.append([500.0 - 5 * k, 300.0, 600.0 - 5 * k, 380.0]), names.append("F")
        if 18 <= k < 30:
            frame.append([600.0, 50.0, 700.0, 120.0]), names.append("Q")
        boxes.append(frame)
        who.append(names)
    asked = []

    def plausible(k_end, i_end, k, i):
        asked.append((who[k_end][i_end], who[k][i]))
        return who[k][i] == "F"

    config = A.AssociateConfig(reacquire=True, stitch_gap=15)
    pick, _ = _follow(boxes, config, plausible)
    for k, names in enumerate(who):
        assert (names[pick[k]] == "F") if "F" in names else pick[k] == -1, (k, pick[k])
    assert asked == [("F", "Q"), ("F", "F")]


def test_a_gap_at_the_image_edge_is_bridged_within_stitch_gap():
    """A car at the right edge goes undetected for 8 frames and comes back where it was, as
    a new track: ``stitch_gap`` 10 bridges the gap; with 5 the car is chosen anew only once
    it has been lost for 6 frames."""
    boxes = [[] if 10 <= k < 18 else [[650.0, 200.0 + k, 752.0, 320.0 + k]] for k in range(30)]
    long, ids = _follow(boxes, A.AssociateConfig(stitch_gap=10))
    assert int(ids[0][0]) != int(ids[29][0])  # the association ended the first track
    np.testing.assert_array_equal(long >= 0, [len(b) > 0 for b in boxes])
    short, _ = _follow(boxes, A.AssociateConfig(stitch_gap=5))
    np.testing.assert_array_equal(short >= 0, long >= 0)  # the only car: chosen anew


def test_the_track_seen_inside_the_image_longest_is_chosen_and_kept_while_seen():
    """Two cars appear together; A's boxes are cut by the border for the first 3 frames, so
    B (inside) is chosen; once chosen B is kept while seen, though A is seen as long."""
    a = [[0.0, 100.0, 100.0, 160.0]]
    b = [[400.0, 100.0, 500.0, 160.0]]
    boxes = [a + b for _ in range(10)]
    inside = [np.array([k >= 3, True]) for k in range(10)]
    pick, _ = _follow(boxes, inside=inside)
    np.testing.assert_array_equal(pick, [1] * 10)
    pick, _ = _follow(boxes)  # all inside: tied, the earliest track
    np.testing.assert_array_equal(pick, [0] * 10)


def test_a_box_the_localisation_refuses_is_neither_matched_nor_stitched():
    """Frame 2's box overlaps the track's, but the check says it is located elsewhere: it
    starts a new track, which the chain does not stitch onto while it waits."""
    boxes = [np.array([[100.0, 100.0, 300.0, 300.0]]) + k for k in range(4)]

    def same(k_a, i_a, k_b, i_b):
        return (k_a < 2) == (k_b < 2)

    pick, ids = _follow(boxes, same=same, associate_same=same)
    assert [int(i[0]) for i in ids] == [0, 0, 1, 1]
    np.testing.assert_array_equal(pick, [0, 0, -1, -1])
    pick, _ = _follow(boxes, associate_same=same)  # unchecked, the chain stitches on
    np.testing.assert_array_equal(pick, [0, 0, 0, 0])


def test_a_chain_does_not_stitch_onto_a_target_boxed_beside_its_last_box():
    """F (followed) and G overlap (IoU > stitch_iou) for 10 frames, then F is gone: G, boxed
    beside F's last box, is another target and is taken only once F is lost."""
    f, g = [100.0, 100.0, 400.0, 400.0], [200.0, 150.0, 380.0, 330.0]
    boxes = [[f, g] if k < 10 else [g] for k in range(30)]
    assert A.box_iou(np.array([f]), np.array([g]))[0, 0] > 0.3
    pick, _ = _follow(boxes)
    gap = A.AssociateConfig().stitch_gap
    np.testing.assert_array_equal(pick[:10], 0)
    np.testing.assert_array_equal(pick[10:10 + gap + 1], -1)
    np.testing.assert_array_equal(pick[10 + gap + 1:], 0)  # lost: G, the only car, chosen


def test_a_doubtful_box_continues_a_track_but_never_starts_one():
    """ByteTrack's two rounds: a box scoring below ``start_score`` keeps a confident box's
    track going (a car seen closer or cut scores lower), is dropped (-1) where it continues
    none (clutter that looks like the class), and loses a track to a confident box."""
    assoc = A.Associator(A.AssociateConfig())
    car = np.array([[100.0, 100.0, 200.0, 160.0]])
    clutter = np.array([400.0, 50.0, 450.0, 90.0])
    start = 0.6
    assert list(assoc.step(car, [0], scores=[0.9], start_score=start)) == [0]
    # the car at a lower score, beside clutter scoring as low: the car's track goes on
    ids = assoc.step(np.stack([car[0] + 5.0, clutter]), [0, 0], scores=[0.4, 0.55],
                     start_score=start)
    assert list(ids) == [0, -1]
    # a doubtful box only takes a track a confident one left unmatched
    ids = assoc.step(np.stack([car[0] + 12.0, car[0] + 8.0]), [0, 0], scores=[0.45, 0.7],
                     start_score=start)
    assert list(ids) == [-1, 0]
    # without scores every box may start a track (the behaviour before the rounds)
    assert list(A.Associator().step(np.stack([car[0], clutter]), [0, 0])) == [0, 1]
    # what a doubtful box could continue: a live track of its class it overlaps
    boxes = np.stack([car[0] + 10.0, clutter, car[0] + 10.0])
    np.testing.assert_array_equal(assoc.could_continue(boxes, [0, 0, 1]), [True, False, False])
    assert not A.Associator().could_continue(boxes, [0, 0, 0]).any()  # no track yet
    for _ in range(A.AssociateConfig().max_missed + 2):  # the car's track ends unmatched
        assoc.step(np.zeros((0, 4)), np.zeros(0, int))
    assert not assoc.could_continue(boxes, [0, 0, 1]).any()
