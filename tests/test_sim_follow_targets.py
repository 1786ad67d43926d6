"""Targets in any flight: the body-frame convention, the camera pitch, and follow targets.

Geometry first (no rendering): a level x-forward/z-up body with ``--camera-pitch 0`` looks
along the body's forward axis, 90 straight down; then the follow planner on a hovering camera;
then one small rendered UZH-FPV flight whose labels must show its follow target in most frames
at the world position its track states.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import shared_path
from scipy.spatial.transform import Rotation

from uavcal_jax.cli import build_parser
from uavcal_jax.commands.simulate import config_from_args
from uavcal_jax.data import read_euroc
from uavcal_jax.data.euroc_rig import EUROC_CAM0_T_BS, EUROC_CAM1_T_BS, euroc_imu_mounting
from uavcal_jax.data.targets import (
    TargetLabels,
    TargetTracks,
    read_target_labels,
    write_target_labels,
)
from uavcal_jax.errors import DataError
from uavcal_jax.sim import follow_targets as ft
from uavcal_jax.sim.config import SimConfig, camera_calibrations, stage_seeds
from uavcal_jax.sim.mounting import pitched_rig, rig_pitch_deg
from uavcal_jax.sim.scene import SceneConfig, target_states
from uavcal_jax.sim.scene_build import MAX_TARGET_HEIGHT, _point_box_distance, make_scene
from uavcal_jax.sim.simulate import load_flight, simulate_report

UZH_INDOOR = ("trajectories", "uzh_fpv", "indoor_forward_3.txt")


def _hover_file(tmp_path, yaw_deg: float = 0.0):
    """A TUM file of a level hover (a quadrotor frame: x forward, z up) yawed ``yaw_deg``."""
    t = np.arange(0.0, 3.0, 0.01)
    q = Rotation.from_euler("z", yaw_deg, degrees=True).as_quat()  # x, y, z, w
    rows = [[ti, 0.01 * np.sin(ti), 0.0, 1.5, *q] for ti in t]
    path = tmp_path / f"hover_{yaw_deg:g}.txt"
    np.savetxt(path, rows, fmt="%.6f")
    return path


def _optical_axes(config: SimConfig) -> np.ndarray:
    """(N, 3) world direction of cam0's optical axis along the configured flight."""
    traj, t_ns, _ = load_flight(config, stage_seeds(config.seed))
    R_WB = traj.state_ns(t_ns[::20]).rotation
    return R_WB @ camera_calibrations(config)["cam0"].T_BS[:3, 2]


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(a @ np.asarray(b, float), -1.0, 1.0)))


@pytest.mark.parametrize("yaw", [0.0, 90.0])
def test_flu_body_pitch_zero_looks_forward_ninety_looks_down(tmp_path, yaw):
    traj = _hover_file(tmp_path, yaw)
    base = dict(trajectory=traj, duration=2.0, body_frame="flu", frames=False)
    forward = np.array([np.cos(np.radians(yaw)), np.sin(np.radians(yaw)), 0.0])
    axis = _optical_axes(SimConfig(**base, camera_pitch_deg=0.0))
    np.testing.assert_allclose(np.degrees(np.arcsin(axis[:, 2])), 0.0, atol=0.05)
    # along body x, up to EuRoC cam0's own 1.5-degree yaw on the rig
    assert np.all(_angle_deg(axis, forward) < 1.6)
    down = _optical_axes(SimConfig(**base, camera_pitch_deg=90.0))
    assert np.all(_angle_deg(down, [0.0, 0.0, -1.0]) < 1.6)
    mid = _optical_axes(SimConfig(**base, camera_pitch_deg=45.0))
    np.testing.assert_allclose(np.degrees(np.arcsin(mid[:, 2])), -45.0, atol=0.05)
    # no pitch given: EuRoC's rig as mounted on EuRoC's MAV, about 20 degrees down
    rig = _optical_axes(SimConfig(**base))
    np.testing.assert_allclose(np.degrees(np.arcsin(rig[:, 2])), -19.756, atol=0.01)


def test_euroc_body_frame_is_the_file_frame(tmp_path):
    """body_frame="euroc" (the default) flies the file's orientations as the IMU's unchanged;
    "flu" mounts EuRoC's IMU on them."""
    traj = _hover_file(tmp_path)
    cfg = SimConfig(trajectory=traj, duration=2.0, frames=False)
    flight, t_ns, info = load_flight(cfg, stage_seeds(0))
    np.testing.assert_allclose(flight.state_ns(t_ns[::50]).rotation, np.eye(3)[None] *
                               np.ones((len(t_ns[::50]), 1, 1)), atol=1e-6)
    assert info["body_frame"] == "euroc"
    flu, t_ns, _ = load_flight(SimConfig(trajectory=traj, duration=2.0, frames=False,
                                         body_frame="flu"), stage_seeds(0))
    np.testing.assert_allclose(flu.state_ns(t_ns[::50]).rotation[0], euroc_imu_mounting(),
                               atol=1e-6)


def test_pitched_rig_keeps_the_stereo_pair_and_default_is_euroc():
    calibs = camera_calibrations(SimConfig())
    np.testing.assert_array_equal(calibs["cam0"].T_BS, EUROC_CAM0_T_BS)
    np.testing.assert_array_equal(calibs["cam1"].T_BS, EUROC_CAM1_T_BS)
    T0, T1 = pitched_rig([EUROC_CAM0_T_BS, EUROC_CAM1_T_BS], 60.0)
    assert rig_pitch_deg(T0) == pytest.approx(60.0, abs=1e-9)
    np.testing.assert_allclose(np.linalg.inv(T0) @ T1,
                               np.linalg.inv(EUROC_CAM0_T_BS) @ EUROC_CAM1_T_BS, atol=1e-12)
    np.testing.assert_allclose(T0[:3, :3].T @ T0[:3, :3], np.eye(3), atol=1e-12)
    # level quadrotor: elevation = -pitch (cam0's small yaw aside)
    axis = euroc_imu_mounting() @ T0[:3, 2]  # the optical axis in the quadrotor frame
    assert np.degrees(np.arcsin(axis[2])) == pytest.approx(-60.0, abs=0.05)


def test_cli_options_map_to_config():
    parser = build_parser()
    args = parser.parse_args(["simulate", "--out", "x", "--body-frame", "flu",
                              "--camera-pitch", "30", "--follow-targets", "2"])
    cfg = config_from_args(args)
    assert (cfg.body_frame, cfg.camera_pitch_deg, cfg.follow_targets) == ("flu", 30.0, 2)
    args = parser.parse_args(["simulate", "--out", "x", "--set", "camera_pitch_deg=45",
                              "body_frame=flu", "follow_targets=1"])
    cfg = config_from_args(args)
    assert (cfg.body_frame, cfg.camera_pitch_deg, cfg.follow_targets) == ("flu", 45.0, 1)
    defaults = config_from_args(parser.parse_args(["simulate", "--out", "x"]))
    assert (defaults.body_frame, defaults.camera_pitch_deg, defaults.follow_targets) == (
        "euroc", None, 0)
    for bad in (dict(body_frame="nwu"), dict(camera_pitch_deg=120.0),
                dict(follow_targets=-1)):
        with pytest.raises(ValueError):
            SimConfig(**bad).validate()


def _hover_request(n: int, seconds: float = 20.0) -> ft.FollowRequest:
    """A camera 3 m above the floor (z = 0), level body, looking 40 degrees down along x."""
    t = np.arange(int(seconds * ft.PLAN_RATE_HZ) + 1) / ft.PLAN_RATE_HZ
    T_BS = pitched_rig([EUROC_CAM0_T_BS], 40.0)[0]
    T_WB = np.eye(4)
    T_WB[:3, :3], T_WB[:3, 3] = euroc_imu_mounting(), [0.0, 0.0, 3.0]
    T_WC = np.broadcast_to(T_WB @ T_BS, (t.size, 4, 4)).copy()
    intr = np.array([114.7, 114.3, 91.8, 62.1])  # EuRoC's cam0 at 188x120
    return ft.FollowRequest(n=n, t=t, T_WC=T_WC, intrinsics=intr, resolution=(188, 120))


def _in_image(req: ft.FollowRequest, points: np.ndarray) -> np.ndarray:
    """(K,) whether the world points (K, 3) project inside the pinhole image."""
    T_CW = np.linalg.inv(req.T_WC)
    p = np.einsum("kij,kj->ki", T_CW[:, :3, :3], points) + T_CW[:, :3, 3]
    fu, fv, cu, cv = req.intrinsics
    u, v = fu * p[:, 0] / p[:, 2] + cu, fv * p[:, 1] / p[:, 2] + cv
    w, h = req.resolution
    return (p[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)


def test_planner_moves_stops_turns_in_view_of_a_hovering_camera():
    req = _hover_request(2)
    half = np.array([[2.1, 0.85, 0.7], [0.25, 0.17, 0.9]])
    tracks = ft.plan_tracks(req, 0.0, np.random.default_rng(4), [0, 1], half)
    assert tracks.shape == (2, req.t.size, 3)
    for i in range(2):
        xy, yaw = tracks[i, :, :2], tracks[i, :, 2]
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=-1) * ft.PLAN_RATE_HZ
        centre = np.concatenate([xy, np.full((xy.shape[0], 1), half[i, 2])], -1)
        assert _in_image(req, centre).mean() > 0.95, i  # in view
        assert speed.max() > 0.4, i  # moves
        still = np.convolve(speed < 0.05, np.ones(10), "valid") == 10
        assert still.any(), i  # stops (half a second at least)
        assert np.ptp(yaw) > 0.5, i  # turns
        assert np.all(np.abs(np.diff(yaw)) < 0.5), i  # heading continuous
    # the two keep apart
    gap = np.linalg.norm(tracks[0, :, :2] - tracks[1, :, :2], axis=-1)
    assert gap.min() > np.hypot(*half[0, :2]) + np.hypot(*half[1, :2])


def test_viewing_floor_puts_the_image_centre_at_the_preferred_distance():
    req = _hover_request(1)
    c, axis = req.T_WC[0, :3, 3], req.T_WC[0, :3, 2]
    for classes, preferred in (([0], ft.PREFERRED_DISTANCE_M[0]), ([1], ft.PREFERRED_DISTANCE_M[1]),
                               ([1, 0], max(ft.PREFERRED_DISTANCE_M))):
        floor = ft.viewing_floor_z(req, classes)
        s = (floor - c[2]) / axis[2]  # along the unit optical axis to the floor
        assert s == pytest.approx(preferred, rel=1e-9), classes
    down = _hover_request(1)
    down.T_WC[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # straight down: the depth is capped
    assert ft.viewing_floor_z(down, [0]) == pytest.approx(c[2] - ft.MAX_VIEWING_DEPTH_M)
    up = _hover_request(1)
    up.T_WC[:, :3, :3] = np.eye(3)  # looks straight up
    assert ft.viewing_floor_z(up, [0]) == float("inf")


def test_make_scene_places_follow_targets_first_off_obstacles_below_the_flight():
    req = _hover_request(2, seconds=6.0)
    path = req.T_WC[:, :3, 3]
    lo, hi = path.min(0), path.max(0)
    coarse = SceneConfig(texel=0.1, target_texel=0.05)  # a small atlas: quick
    scn = make_scene(lo, hi, seed=2, config=coarse, path_points=path, follow=req)
    tg = scn.targets
    tracked = np.asarray(tg.tracked)
    assert tracked[:2].all() and not tracked[2:].any()
    assert list(np.asarray(tg.class_id)[:2]) == [0, 1]
    floor = float(scn.room_lo[2])
    assert lo[2] - floor >= MAX_TARGET_HEIGHT  # no target reaches the drone
    assert floor <= ft.viewing_floor_z(req, [0, 1]) + 1e-5  # and the car can be seen whole
    np.testing.assert_allclose(np.asarray(tg.z)[:2], floor + np.asarray(tg.half_extents)[:2, 2],
                               atol=1e-5)
    track = np.asarray(tg.track)[:2]
    assert np.all(track[:, :, :2] > np.asarray(scn.room_lo)[:2]) and np.all(
        track[:, :, :2] < np.asarray(scn.room_hi)[:2])
    # every obstacle keeps clear of every track point (box distance > the target's reach)
    reach = np.hypot(*np.asarray(tg.half_extents)[:2, :2].T)
    for k in range(1, scn.n_static):
        for i in range(2):
            pts = np.concatenate([track[i, :, :2], np.full((track.shape[1], 1),
                                                           float(tg.z[i]))], -1)
            d = _point_box_distance(pts, np.asarray(scn.box_center[k]),
                                    float(scn.box_yaw[k]), np.asarray(scn.box_half[k]))
            assert d.min() > reach[i], (k, i)
    # the renderer's pose is the track, interpolated
    pos, yaw, vel = (np.asarray(a) for a in target_states(scn, 1.025))
    np.testing.assert_allclose(pos[0, :2], track[0, 20:22, :2].mean(0), atol=1e-4)
    np.testing.assert_allclose(vel[0, :2], np.diff(track[0, 20:22, :2], axis=0)[0]
                               * ft.PLAN_RATE_HZ, atol=1e-3)


def test_labels_without_track_file_still_read(tmp_path):
    labels = TargetLabels(np.array([5]), np.array(["cam0"]), np.array([0]), np.array([1]),
                          np.array([[1.0, 2.0, 3.0, 4.0]]), np.array([4]),
                          np.array([[0.5, 0.6, 0.7]]), ("car", "person"))
    write_target_labels(tmp_path / "old", labels)
    assert read_target_labels(tmp_path / "old").tracks is None
    tracks = TargetTracks(np.array([5, 10]), np.array([0, 1]), np.array([1, 0]),
                          np.arange(12.0).reshape(2, 2, 3), np.array([[0.1, 0.2], [0.3, 0.4]]),
                          -np.arange(12.0).reshape(2, 2, 3))
    write_target_labels(tmp_path / "new", TargetLabels(**{**labels.__dict__, "tracks": tracks}))
    back = read_target_labels(tmp_path / "new").tracks
    for name in ("t_ns", "track_id", "class_id", "position", "yaw", "velocity"):
        np.testing.assert_allclose(getattr(back, name), getattr(tracks, name), atol=1e-6)
    csv = tmp_path / "new" / "track.csv"
    csv.write_text("\n".join(csv.read_text().splitlines()[:-1]) + "\n")  # a row short
    with pytest.raises(DataError, match="track.csv"):
        read_target_labels(tmp_path / "new")


# --- one rendered UZH-FPV flight -------------------------------------------------------------

UZH = dict(start=5.0, duration=4.0, body_frame="flu", camera_pitch_deg=20.0, follow_targets=1,
           resolution=(188, 120), depth=False, ideal_camera=True)


@pytest.fixture(scope="module")
def uzh_sim(tmp_path_factory):
    path = shared_path(*UZH_INDOOR)
    config = SimConfig(trajectory=path, **UZH)
    root = tmp_path_factory.mktemp("follow") / "rec"
    simulate_report(config, root, progress=False)
    return root, config


def test_uzh_flight_sees_its_follow_target(uzh_sim):
    root, config = uzh_sim
    record = json.loads((root / "sim_config.json").read_text())
    assert record["config"]["body_frame"] == "flu"
    assert record["config"]["camera_pitch_deg"] == 20.0
    assert record["config"]["follow_targets"] == 1
    seq = read_euroc(root)
    calib = seq.cameras["cam0"].calibration
    np.testing.assert_allclose(calib.T_BS, camera_calibrations(config)["cam0"].T_BS,
                               atol=1e-9)  # sensor.yaml states the pitched rig
    labels, tracks = seq.targets, seq.targets.tracks
    assert tracks is not None and tracks.class_id[0] == 0  # target 0 is the (car) follow target
    frames = seq.cameras["cam0"].t_ns
    np.testing.assert_array_equal(tracks.t_ns, frames)
    mine = (labels.camera == "cam0") & (labels.track_id == 0)
    assert np.isin(frames, labels.t_ns[mine]).mean() >= 0.8
    assert np.linalg.norm(np.ptp(tracks.position[:, 0, :2], axis=0)) > 1.0  # it moves
    gt = seq.ground_truth
    row_of = {int(t): i for i, t in enumerate(gt.t_ns)}
    frame_of = {int(t): k for k, t in enumerate(tracks.t_ns)}
    checked = 0
    for r in np.flatnonzero(mine & (labels.visible_pixels >= 40)):
        k = frame_of[int(labels.t_ns[r])]
        np.testing.assert_allclose(labels.position[r], tracks.position[k, 0], atol=1e-5)
        i = row_of[int(labels.t_ns[r])]
        T_WB = np.eye(4)
        T_WB[:3, :3] = Rotation.from_quat(gt.quaternion[i][[1, 2, 3, 0]]).as_matrix()
        T_WB[:3, 3] = gt.position[i]
        T_CW = np.linalg.inv(T_WB @ calib.T_BS)
        p = T_CW[:3, :3] @ labels.position[r] + T_CW[:3, 3]
        assert p[2] > 0
        uv, _ = cv2.projectPoints(p[None], np.zeros(3), np.zeros(3), calib.K, calib.distortion)
        u, v = uv.ravel()
        box = labels.box[r]
        lo = np.where(box[:2] > 0, box[:2] - 2, -np.inf)
        hi = np.where(box[2:] < (188, 120), box[2:] + 2, np.inf)
        assert lo[0] <= u <= hi[0] and lo[1] <= v <= hi[1], (r, u, v, box)
        checked += 1
    assert checked >= 0.5 * mine.sum()
