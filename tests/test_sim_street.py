"""Vehicles of real fleets, street scenes and nadir frames: the drawn paints and kinds follow
their shares, every kind's label box is its projected silhouette, a car seen from 50 m is
``L f / (altitude - height)`` pixels long, and the nadir set reads back as a YOLO folder."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.detect.datasets import load_dataset
from uavcal_jax.sim.nadir_set import nadir_camera, nadir_pose, nadir_street_set
from uavcal_jax.sim.render import render
from uavcal_jax.sim.scene import CAR
from uavcal_jax.sim.scene_build import MAX_TARGET_HEIGHT
from uavcal_jax.sim.street_scene import MAX_TARGETS, street_scene
from uavcal_jax.sim.target_boxes import target_boxes
from uavcal_jax.sim.vehicles import KINDS, PAINTS, PASSENGER_KINDS, draw_paint, draw_vehicle

ALTITUDE = 50.0


def test_paints_and_kinds_follow_their_shares():
    rng = np.random.default_rng(0)
    n = 6000
    paints = np.bincount([draw_paint(rng)[0] for _ in range(n)], minlength=len(PAINTS)) / n
    want = np.array([p[1] for p in PAINTS])
    np.testing.assert_allclose(paints, want / want.sum(), atol=0.02)
    # white, black, grey and silver: about three quarters of a real fleet
    assert 0.7 < paints[:4].sum() < 0.82
    vehicles = [draw_vehicle(rng) for _ in range(3000)]
    names = [k.name for k in KINDS]
    kinds = np.bincount([names.index(v.kind.name) for v in vehicles], minlength=len(KINDS))
    shares = np.array([k.share for k in KINDS])
    np.testing.assert_allclose(kinds / len(vehicles), shares / shares.sum(), atol=0.025)
    for v in vehicles:  # sizes inside the kind's ranges
        lo = 0.5 * np.array([v.kind.length[0], v.kind.width[0], v.kind.height[0]])
        hi = 0.5 * np.array([v.kind.length[1], v.kind.width[1], v.kind.height[1]])
        assert np.all(v.half >= lo) and np.all(v.half <= hi)
    lengths = [2 * v.half[0] for v in vehicles]
    assert min(lengths) < 3.9 and max(lengths) > 11.0
    hall = [draw_vehicle(rng, PASSENGER_KINDS) for _ in range(200)]
    assert max(2 * v.half[2] for v in hall) <= MAX_TARGET_HEIGHT


@pytest.fixture(scope="module")
def kinds_scene():
    """A street scene whose first targets are one vehicle of each kind in a column under the
    camera (x = 0, yaw 0, 4 m apart in y); the other slots hidden."""
    scn = street_scene(3, (30.0, 30.0), 0.1)
    rng = np.random.default_rng(1)
    n = len(KINDS)
    half = np.asarray(scn.targets.half_extents).copy()
    center = np.asarray(scn.targets.center).copy()
    z = np.full(MAX_TARGETS, -1000.0, np.float32)
    yaw = np.zeros(MAX_TARGETS, np.float32)
    cls = np.asarray(scn.targets.class_id).copy()
    for i, kind in enumerate(KINDS):
        half[i] = draw_vehicle(rng, (kind.name,)).half
        center[i] = [0.0, 4.0 * (i - 0.5 * (n - 1))]
        z[i] = half[i, 2]
        cls[i] = CAR
    tg = dataclasses.replace(scn.targets, half_extents=jnp.asarray(half),
                             center=jnp.asarray(center), z=jnp.asarray(z), yaw=jnp.asarray(yaw),
                             class_id=jnp.asarray(cls))
    # clear the static boxes above the floor (trees, buildings) so that nothing hides them
    bc = np.asarray(scn.box_center).copy()
    bc[1:, 2] = -1000.0
    return dataclasses.replace(scn, targets=tg, box_center=jnp.asarray(bc)), half[:n]


def test_label_box_of_every_kind_is_its_projected_silhouette(kinds_scene):
    scn, half = kinds_scene
    cam = nadir_camera((640, 480), 70.0)
    T = nadir_pose((0.0, 0.0), ALTITUDE, 0.0)
    out = render(scn, cam, T, 0.0, color="rgb")
    boxes, count = target_boxes(out.object_id, scn.n_targets)
    boxes, count = np.asarray(boxes), np.asarray(count)
    f, cx, cy = float(cam.fx), float(cam.cx), float(cam.cy)
    T_CW = np.linalg.inv(T)
    signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    center = np.asarray(scn.targets.center)
    for i, h in enumerate(half):
        corners = np.array([center[i, 0], center[i, 1], h[2]]) + signs * h
        pc = corners @ T_CW[:3, :3].T + T_CW[:3, 3]
        u, v = f * pc[:, 0] / pc[:, 2] + cx, f * pc[:, 1] / pc[:, 2] + cy
        # the pixels whose centres fall inside the projected box
        want = [np.ceil(u.min()), np.ceil(v.min()), np.floor(u.max()) + 1, np.floor(v.max()) + 1]
        assert count[i] > 0, KINDS[i].name
        np.testing.assert_allclose(boxes[i], want, atol=1.0, err_msg=KINDS[i].name)
        # seen from straight above, the roof spans the box: L f / (altitude - height) pixels
        length_px = 2 * h[0] * f / (ALTITUDE - 2 * h[2])
        assert abs((boxes[i, 2] - boxes[i, 0]) - length_px) <= 1.0, KINDS[i].name
    assert np.all(count[len(half):] == 0)  # hidden slots are never seen


def test_nadir_street_set_reads_back_as_yolo(tmp_path):
    root = nadir_street_set(tmp_path / "nadir", 1, seed=5, altitude=(30.0, 30.0),
                            resolution=(160, 120), progress=False)
    ds = load_dataset(root, "yolo")
    assert ds.class_names == ("car", "person")
    assert len(ds.records) == 1
    rec = ds.records[0]
    assert (rec.width, rec.height) == (160, 120)
    assert len(rec.boxes) >= 3 and np.all(rec.classes[rec.classes >= 0] <= 1)
    # a car is at least 3.7 m long: above 3.7 f / 30 pixels along its longer side
    f = float(nadir_camera((160, 120)).fx)
    sides = np.maximum(rec.boxes[:, 2] - rec.boxes[:, 0], rec.boxes[:, 3] - rec.boxes[:, 1])
    assert np.median(sides[rec.classes == 0]) > 0.8 * 3.7 * f / 30.0
