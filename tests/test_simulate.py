"""The simulator's output: EuRoC ASL writer and the orchestration of ``simulate``."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import warnings
from pathlib import Path

import cv2
import jax
import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.data import (
    camera_calibration_from_yaml,
    imu_calibration_from_yaml,
    read_euroc,
    read_sensor_yaml,
)
from uavcal_jax.data.euroc_format import GROUND_TRUTH_HEADER, IMU_HEADER
from uavcal_jax.data.euroc_rig import euroc_calibration
from uavcal_jax.data.euroc_writer import (
    EurocWriter,
    camera_sensor_yaml,
    depth_to_millimetres,
    ground_truth_sensor_yaml,
    imu_sensor_yaml,
)
from uavcal_jax.data.sequence import CameraCalibration, GroundTruth, ImuCalibration, ImuData
from uavcal_jax.data.targets import TargetLabels
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError, DataRepairWarning
from uavcal_jax.imu.noise import ImuNoise
from uavcal_jax.imu.offset import remove_offset
from uavcal_jax.sim.config import (
    IDEAL_SENSORS,
    SimConfig,
    camera_calibrations,
    scale_calibration,
    sensor_model,
    stage_seeds,
)
from uavcal_jax.sim.imu_synth import synthesize_imu
from uavcal_jax.sim.simulate import (
    imu_calibration,
    imu_error_options,
    intrinsic_error,
    load_flight,
    simulate,
    simulate_report,
)

EUROC_IMU = ImuCalibration(rate_hz=200.0, T_BS=np.eye(4),
                           noise=ImuNoise(gyro_noise_density=1.6968e-04,
                                          gyro_random_walk=1.9393e-05,
                                          accel_noise_density=2.0e-3, accel_random_walk=3.0e-3))


def _read_strict(root):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataRepairWarning)
        return read_euroc(root, strict=True)


def _skeleton(text: str) -> list[str]:
    """A sensor.yaml's layout: keys, comments and blank lines, numbers blanked out."""
    out = []
    for line in text.splitlines():
        line = re.sub(r"[-+]?\d[\d.e+-]*", "N", line)
        out.append(re.sub(r"\s+", " ", line).strip())
    return [line for line in out if line]


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


@pytest.mark.realdata
@pytest.mark.parametrize("sensor", ["cam0", "cam1", "imu0", "state_groundtruth_estimate0"])
def test_sensor_yaml_layout_matches_euroc(euroc_micro, sensor, tmp_path):
    """Our sensor.yaml files have EuRoC's exact layout and read back to the same values."""
    real_path = euroc_micro / "mav0" / sensor / "sensor.yaml"
    real_text = real_path.read_text()
    comment = re.search(r"^comment: (.*)$", real_text, re.M).group(1)
    real_parsed = read_sensor_yaml(real_path)
    if sensor.startswith("cam"):
        ours = camera_sensor_yaml(camera_calibration_from_yaml(real_parsed), comment)
    elif sensor == "imu0":
        ours = imu_sensor_yaml(imu_calibration_from_yaml(real_parsed), comment)
    else:
        ours = ground_truth_sensor_yaml(comment)
    assert ours.startswith("%YAML:1.0\n")
    assert _skeleton(ours) == _skeleton(real_text)
    (tmp_path / "sensor.yaml").write_text(ours)
    ours_parsed = read_sensor_yaml(tmp_path / "sensor.yaml")
    assert ours_parsed.keys() == real_parsed.keys()
    for key, value in real_parsed.items():
        if isinstance(value, str):
            assert ours_parsed[key] == value
        else:
            np.testing.assert_array_equal(np.asarray(ours_parsed[key], float),
                                          np.asarray(value, float))


@pytest.mark.realdata
def test_csv_headers_match_euroc(euroc_micro):
    mav0 = euroc_micro / "mav0"
    assert (mav0 / "imu0" / "data.csv").open().readline().rstrip("\n") == IMU_HEADER
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    assert gt_csv.open().readline().rstrip("\n") == GROUND_TRUTH_HEADER


def test_depth_to_millimetres():
    d = np.array([[0.0, 1.0, 2.5004], [np.inf, np.nan, 70.0]], dtype=np.float32)
    mm = depth_to_millimetres(d)
    assert mm.dtype == np.uint16
    np.testing.assert_array_equal(mm, [[0, 1000, 2500], [0, 0, 0]])


def test_writer_round_trip(tmp_path):
    """Everything written reads back exactly with read_euroc (strict: no repairs needed)."""
    rng = np.random.default_rng(0)
    n_imu, n_cam = 41, 5
    t_imu = 1_403_715_274_302_140_000 + np.arange(n_imu, dtype=np.int64) * 5_000_000
    imu = ImuData(t_imu, rng.normal(size=(n_imu, 3)), rng.normal(size=(n_imu, 3)) + 9.81)
    q = rng.normal(size=(n_imu, 4))
    gt = GroundTruth(t_imu, rng.normal(size=(n_imu, 3)), q / np.linalg.norm(q, axis=1)[:, None],
                     rng.normal(size=(n_imu, 3)), rng.normal(size=(n_imu, 3)) * 1e-3,
                     rng.normal(size=(n_imu, 3)) * 1e-2)
    calib = dataclasses.replace(euroc_calibration(0), resolution=(64, 40))
    t_cam = t_imu[::10]
    images = rng.integers(0, 256, size=(n_cam, 40, 64), dtype=np.uint8)
    depths = rng.integers(0, 20000, size=(n_cam, 40, 64)).astype(np.uint16)
    labels = TargetLabels(t_cam[[0, 2]], np.array(["cam0", "cam1"]), np.array([0, 1]),
                          np.array([1, 0]), np.array([[1.0, 2.0, 10.0, 12.0], [0, 0, 5, 5]]),
                          np.array([50, 25]), np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
                          ("person", "car"))
    with EurocWriter(tmp_path / "rec") as w:
        w.add_image_stream("cam0", calib, comment="test cam0")
        w.add_image_stream("depth0", calib, comment="test depth0", depth=True)
        for i in range(n_cam):
            w.write_frame("cam0", t_cam[i], images[i])
            w.write_frame("depth0", t_cam[i], depths[i])
        w.write_imu(imu, EUROC_IMU, comment="test imu")
        w.write_ground_truth(gt)
        w.write_targets(labels)

    seq = _read_strict(tmp_path / "rec")
    np.testing.assert_array_equal(seq.imu.t_ns, imu.t_ns)
    np.testing.assert_array_equal(seq.imu.gyro, imu.gyro)
    np.testing.assert_array_equal(seq.imu.accel, imu.accel)
    assert seq.imu_calibration.noise.gyro_noise_density == EUROC_IMU.noise.gyro_noise_density
    assert seq.imu_calibration.noise.accel_random_walk == EUROC_IMU.noise.accel_random_walk
    for name in ("position", "quaternion", "velocity", "bias_gyro", "bias_accel"):
        np.testing.assert_array_equal(getattr(seq.ground_truth, name), getattr(gt, name))
    cam = seq.cameras["cam0"]
    np.testing.assert_array_equal(cam.t_ns, t_cam)
    _assert_calib_equal(cam.calibration, calib)
    for i in range(n_cam):
        np.testing.assert_array_equal(cam.load(i), images[i])
        np.testing.assert_array_equal(seq.depth["depth0"].load(i),
                                      depths[i].astype(np.float32) * np.float32(1e-3))
    assert read_sensor_yaml(tmp_path / "rec/mav0/depth0/sensor.yaml")["sensor_type"] == "depth"
    assert seq.targets.class_names == ("person", "car")
    np.testing.assert_array_equal(seq.targets.box, labels.box)
    np.testing.assert_array_equal(seq.targets.camera, labels.camera)


def test_writer_rgb_frames_are_rgb(tmp_path):
    calib = dataclasses.replace(euroc_calibration(1), resolution=(16, 8))
    img = np.zeros((8, 16, 3), np.uint8)
    img[..., 0] = 200  # red
    with EurocWriter(tmp_path) as w:
        w.add_image_stream("cam1", calib, comment="rgb")
        w.write_frame("cam1", 1000, img)
    bgr = cv2.imread(str(tmp_path / "mav0/cam1/data/1000.png"), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(bgr[..., 2], 200)
    np.testing.assert_array_equal(bgr[..., :2], 0)


def test_writer_refuses_non_empty_folder(tmp_path):
    (tmp_path / "mav0").mkdir()
    (tmp_path / "mav0" / "junk").write_text("x")
    with pytest.raises(DataError, match="not empty"):
        EurocWriter(tmp_path)


def _assert_calib_equal(a: CameraCalibration, b: CameraCalibration) -> None:
    np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
    np.testing.assert_array_equal(a.distortion, b.distortion)
    np.testing.assert_array_equal(a.T_BS, b.T_BS)
    assert tuple(a.resolution) == tuple(b.resolution)
    assert a.rate_hz == b.rate_hz


# --------------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------------

SMALL = SimConfig(duration=1.0, resolution=(160, 100), seed=3)


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    """One short rendered simulation shared by the tests below (compiles the renderer once)."""
    root = tmp_path_factory.mktemp("sim") / "rec"
    report = simulate_report(SMALL, root, progress=False)
    return root, report


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _flight(config: SimConfig):
    traj, t_ns, _ = load_flight(config, stage_seeds(config.seed))
    return traj, t_ns


def test_simulation_reads_back(small_sim):
    root, report = small_sim
    seq = _read_strict(root)
    n_imu, n_cam = 201, 21  # 1 s at 200 Hz and 20 Hz, both ends included
    assert len(seq.imu) == n_imu and len(seq.ground_truth) == n_imu
    assert sorted(seq.cameras) == ["cam0", "cam1"]
    assert sorted(seq.depth) == ["depth0", "depth1"]
    assert np.all(np.diff(seq.imu.t_ns) == 5_000_000)
    calibs = camera_calibrations(SMALL)
    for i, name in enumerate(("cam0", "cam1")):
        cam, depth = seq.cameras[name], seq.depth[f"depth{i}"]
        assert len(cam) == n_cam and len(depth) == n_cam
        assert np.all(np.diff(cam.t_ns) == 50_000_000)
        np.testing.assert_array_equal(cam.t_ns, seq.imu.t_ns[::10])  # triggered with the IMU
        np.testing.assert_array_equal(depth.t_ns, cam.t_ns)
        _assert_calib_equal(cam.calibration, calibs[name])
        _assert_calib_equal(depth.calibration, calibs[name])
        assert cam.load(0).shape == (100, 160) and cam.load(0).dtype == np.uint8
        d = depth.load(n_cam // 2)
        assert d.shape == (100, 160)
        assert (d > 0).mean() > 0.99  # a closed hall: every ray hits something
        assert d.max() < 50.0
    # Intrinsics scaled from EuRoC's 752x480, same field of view.
    np.testing.assert_allclose(calibs["cam0"].intrinsics[:2],
                               euroc_calibration(0).intrinsics[:2] * [160 / 752, 100 / 480])
    _assert_imu_calib_equal(seq.imu_calibration, imu_calibration(SMALL))
    assert seq.imu_calibration.rate_hz == 200.0
    resolved = json.loads((root / "sim_config.json").read_text())
    assert resolved["config"] == SMALL.to_dict()
    assert resolved["counts"]["frames"] == n_cam
    # the camera model is on by default and recorded
    camera = resolved["camera_model"]
    assert not camera["ideal"] and camera["noise"] and camera["blur_samples"] == SMALL.blur_samples
    assert camera["sensor"] == json.loads(json.dumps(sensor_model(SMALL).to_dict()))
    assert camera["noise_seed"] == stage_seeds(SMALL.seed)["camera"] == resolved["seeds"]["camera"]


def _assert_imu_calib_equal(a: ImuCalibration, b: ImuCalibration) -> None:
    np.testing.assert_array_equal(a.T_BS, b.T_BS)
    for f in dataclasses.fields(ImuCalibration):
        if f.name != "T_BS":
            assert getattr(a, f.name) == getattr(b, f.name), f.name


def test_target_labels(small_sim):
    root, report = small_sim
    seq = _read_strict(root)
    tg = seq.targets
    assert tg is not None and len(tg) > 0, "the scene's targets should be seen"
    assert set(np.unique(tg.camera)) <= {"cam0", "cam1"}
    assert set(tg.t_ns) <= set(seq.cameras["cam0"].t_ns.tolist())
    assert np.all(tg.visible_pixels > 0)
    assert np.all((tg.box[:, 0] < tg.box[:, 2]) & (tg.box[:, 1] < tg.box[:, 3]))
    assert np.all(tg.box >= 0)
    assert np.all(tg.box[:, [0, 2]] <= 160) and np.all(tg.box[:, [1, 3]] <= 100)
    assert np.all(tg.visible_pixels <= (tg.box[:, 2] - tg.box[:, 0]) *
                  (tg.box[:, 3] - tg.box[:, 1]))
    # The target's world position, seen from the ground-truth pose, projects near its box.
    gt = seq.ground_truth
    row_of = {int(t): i for i, t in enumerate(gt.t_ns)}
    from scipy.spatial.transform import Rotation

    checked = 0
    for r in range(len(tg)):
        box = tg.box[r]
        if tg.visible_pixels[r] < 40:
            continue
        i = row_of[int(tg.t_ns[r])]
        T_WB = np.eye(4)
        T_WB[:3, :3] = Rotation.from_quat(gt.quaternion[i][[1, 2, 3, 0]]).as_matrix()
        T_WB[:3, 3] = gt.position[i]
        calib = seq.cameras[str(tg.camera[r])].calibration
        T_CW = np.linalg.inv(T_WB @ calib.T_BS)
        p = T_CW[:3, :3] @ tg.position[r] + T_CW[:3, 3]
        assert p[2] > 0
        uv, _ = cv2.projectPoints(p[None], np.zeros(3), np.zeros(3), calib.K, calib.distortion)
        u, v = uv.ravel()
        # Inside the box, except beyond a side the image border cuts (the centre may be
        # outside the image there).
        lo = np.where(box[:2] > 0, box[:2] - 2, -np.inf)
        hi = np.where(box[2:] < (160, 100), box[2:] + 2, np.inf)
        assert lo[0] <= u <= hi[0] and lo[1] <= v <= hi[1], (r, u, v, box)
        checked += 1
    assert checked > 0


def test_ground_truth_equals_trajectory(small_sim):
    root, _ = small_sim
    seq = _read_strict(root)
    traj, t_ns = _flight(SMALL)
    gt = seq.ground_truth
    np.testing.assert_array_equal(gt.t_ns, t_ns)
    state = traj.state_ns(gt.t_ns)
    np.testing.assert_array_equal(gt.position, state.position)
    np.testing.assert_array_equal(gt.quaternion, state.quaternion)
    np.testing.assert_array_equal(gt.velocity, state.velocity)
    # The IMU is the exact IMU (with the configuration's vibration, scale, misalignment and
    # g-sensitivity: EuRoC's by default) plus the sensor's biases plus white noise; the ground
    # truth's bias columns are those biases plus the intrinsics' error on the motion.
    exact = synthesize_imu(traj, 200.0, None, stage_seeds(SMALL.seed)["imu"], t_ns=t_ns,
                           **imu_error_options(SMALL)).imu
    extra_g, extra_a = intrinsic_error(traj, t_ns, SMALL)
    assert np.abs(extra_a).max() > 1e-3  # the default IMU has them
    white_g = seq.imu.gyro - exact.gyro - (gt.bias_gyro - extra_g)
    white_a = seq.imu.accel - exact.accel - (gt.bias_accel - extra_a)
    noise = ImuNoise()
    np.testing.assert_allclose(white_g.std(), noise.gyro_noise_density * np.sqrt(200), rtol=0.15)
    np.testing.assert_allclose(white_a.std(), noise.accel_noise_density * np.sqrt(200),
                               rtol=0.15)
    assert np.abs(gt.bias_gyro).max() > 1e-4  # turn-on biases are there


def test_same_seed_same_files_different_seed_differs(small_sim, tmp_path):
    root, _ = small_sim
    simulate(SMALL, tmp_path / "again", progress=False)
    assert _hashes(tmp_path / "again") == _hashes(root)
    other = dataclasses.replace(SMALL, seed=4, frames=False)
    simulate(other, tmp_path / "other", progress=False)
    h_other = _hashes(tmp_path / "other")
    h_root = _hashes(root)
    for name in ("mav0/imu0/data.csv", "mav0/state_groundtruth_estimate0/data.csv"):
        assert h_other[name] != h_root[name]


def test_no_frames_and_exact_imu(tmp_path):
    config = SimConfig(duration=2.0, seed=5, frames=False, imu_noise=False)
    simulate(config, tmp_path / "rec", progress=False)
    mav0 = tmp_path / "rec" / "mav0"
    assert sorted(p.name for p in mav0.iterdir() if p.is_dir()) == [
        "imu0", "state_groundtruth_estimate0"]
    seq = _read_strict(tmp_path / "rec")
    assert seq.cameras == {} and seq.depth == {} and seq.targets is None
    traj, t_ns = _flight(config)
    exact = synthesize_imu(traj, 200.0, None, stage_seeds(config.seed)["imu"], t_ns=t_ns,
                           **imu_error_options(config))
    np.testing.assert_array_equal(seq.imu.t_ns, exact.imu.t_ns)
    np.testing.assert_array_equal(seq.imu.gyro, exact.imu.gyro)
    np.testing.assert_array_equal(seq.imu.accel, exact.imu.accel)
    # no sensor bias: the bias columns are the intrinsics' error alone
    extra_g, extra_a = intrinsic_error(traj, t_ns, config)
    np.testing.assert_allclose(seq.ground_truth.bias_gyro, extra_g, rtol=0, atol=1e-12)
    np.testing.assert_allclose(seq.ground_truth.bias_accel, extra_a, rtol=0, atol=1e-12)
    ideal = SimConfig(duration=2.0, seed=5, frames=False, imu_noise=False, **IDEAL_SENSORS)
    simulate(ideal, tmp_path / "ideal", progress=False)
    np.testing.assert_array_equal(_read_strict(tmp_path / "ideal").ground_truth.bias_accel, 0.0)


def test_imu_offset_is_an_extra_constant_error(tmp_path):
    """The offset rides on top of the noisy IMU: the ground truth (and its true biases) is that
    of the run without it, and removing the recorded offset gives that run's IMU back."""
    offset = (0.03, -0.05, 0.01, -0.3, 0.2, 0.12)
    clean_cfg = SimConfig(duration=2.0, seed=6, frames=False)
    simulate(clean_cfg, tmp_path / "clean", progress=False)
    simulate(dataclasses.replace(clean_cfg, imu_offset=offset), tmp_path / "miscal",
             progress=False)
    clean, miscal = _read_strict(tmp_path / "clean"), _read_strict(tmp_path / "miscal")
    recorded = json.loads((tmp_path / "miscal" / "sim_config.json").read_text())
    assert recorded["config"]["imu_offset"] == list(offset)
    np.testing.assert_array_equal(miscal.imu.t_ns, clean.imu.t_ns)
    for name in ("position", "quaternion", "velocity", "bias_gyro", "bias_accel"):
        np.testing.assert_array_equal(getattr(miscal.ground_truth, name),
                                      getattr(clean.ground_truth, name), err_msg=name)
    assert np.abs(clean.ground_truth.bias_accel).max() > 1e-3  # noise and biases are there
    np.testing.assert_allclose(miscal.imu.gyro - clean.imu.gyro,
                               np.broadcast_to(offset[:3], clean.imu.gyro.shape), atol=1e-14)
    np.testing.assert_allclose(miscal.imu.accel - clean.imu.accel,
                               np.broadcast_to(offset[3:], clean.imu.accel.shape), atol=1e-13)
    with jax.enable_x64(True):
        gyro, accel = remove_offset(miscal.imu.gyro, miscal.imu.accel,
                                    np.asarray(recorded["config"]["imu_offset"]))
    np.testing.assert_allclose(np.asarray(gyro), clean.imu.gyro, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(accel), clean.imu.accel, rtol=0, atol=1e-13)
    assert "offset" in (tmp_path / "miscal" / "mav0" / "imu0" / "sensor.yaml").read_text()


@pytest.mark.parametrize("bad", [(0.1,) * 5, (0.1,) * 7, (0, 0, float("nan"), 0, 0, 0),
                                 (0, 0, 0, float("inf"), 0, 0)])
def test_imu_offset_is_validated(bad):
    with pytest.raises(ValueError, match="imu_offset"):
        SimConfig(imu_offset=bad).validate()
    with pytest.raises(ValueError):
        SimConfig(imu_offset=("a", 0, 0, 0, 0, 0))
    assert SimConfig(imu_offset=np.arange(6)).imu_offset == (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)


def test_procedural_imu_is_mounted_like_euroc(tmp_path):
    """EuRoC's IMU x axis points up (gravity reads ~+9.8 on x), its z axis (the cameras'
    optical axis) forward and ~20 degrees down."""
    config = SimConfig(duration=1.0, seed=1, frames=False, imu_noise=False)
    traj, t_ns = _flight(config)
    accel = synthesize_imu(traj, 200.0, None, t_ns=t_ns[:1]).imu.accel[0]  # hovering
    np.testing.assert_allclose(accel / np.linalg.norm(accel),
                               [np.cos(np.radians(20)), 0.0, -np.sin(np.radians(20))], atol=1e-3)


@pytest.mark.realdata
def test_trajectory_file_keeps_its_clock(tmp_path):
    path = shared_path("trajectories", "euroc", "V1_01_easy.txt")
    tum = read_tum(path)
    config = SimConfig(trajectory=str(path), start=2.0, duration=1.0, frames=False,
                       imu_noise=False)
    simulate(config, tmp_path / "rec", progress=False)
    seq = _read_strict(tmp_path / "rec")
    first = int(tum.t_ns[0])
    assert seq.imu.t_ns[0] == first + 2_000_000_000
    assert tum.t_ns[0] <= seq.imu.t_ns[0] and seq.imu.t_ns[-1] <= tum.t_ns[-1]
    np.testing.assert_array_equal(seq.ground_truth.t_ns, seq.imu.t_ns)
    # The file is 200 Hz: the simulated states sit on its own timestamps, close to its poses.
    idx = np.searchsorted(tum.t_ns, seq.ground_truth.t_ns)
    np.testing.assert_array_equal(tum.t_ns[idx], seq.ground_truth.t_ns)
    assert np.abs(seq.ground_truth.position - tum.position[idx]).max() < 0.005
    dots = np.abs(np.sum(seq.ground_truth.quaternion * tum.quaternion[idx], axis=1))
    assert np.degrees(2 * np.arccos(np.minimum(dots, 1.0))).max() < 0.5
    # a recorded flight: both vibration spectra (in flight, standing) are in the record
    resolved = json.loads((tmp_path / "rec" / "sim_config.json").read_text())
    assert resolved["imu_rest_vibration_spectrum"]["bands"][0]["freq_hz"] == pytest.approx(
        17.56)
    assert "imu_vibration_spectrum" in resolved


@pytest.mark.realdata
def test_trajectory_window_outside_the_file(tmp_path):
    path = shared_path("trajectories", "euroc", "V1_01_easy.txt")
    with pytest.raises(DataError, match="past the end") as err:
        simulate(SimConfig(trajectory=str(path), start=1000.0, frames=False), tmp_path / "a",
                 progress=False)
    assert str(path) in str(err.value)
    with pytest.raises(DataError, match="runs past the end") as err:
        simulate(SimConfig(trajectory=str(path), start=140.0, duration=10.0, frames=False),
                 tmp_path / "b", progress=False)
    assert str(path) in str(err.value)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_missing_trajectory_file(tmp_path):
    path = tmp_path / "nope.txt"
    with pytest.raises(DataError) as err:
        simulate(SimConfig(trajectory=str(path), frames=False), tmp_path / "out", progress=False)
    assert str(path) in str(err.value)


def test_output_folder_rules(tmp_path):
    config = SimConfig(duration=0.5, frames=False)
    out = tmp_path / "rec"
    out.mkdir()  # an empty folder is fine
    simulate(config, out, progress=False)
    with pytest.raises(DataError, match="--overwrite"):
        simulate(config, out, progress=False)
    simulate(dataclasses.replace(config, seed=9), out, progress=False, overwrite=True)
    assert json.loads((out / "sim_config.json").read_text())["config"]["seed"] == 9
    other = tmp_path / "precious"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(DataError, match="not a previous simulation"):
        simulate(config, other, progress=False, overwrite=True)
    assert (other / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious", "rec"]  # no leftovers


def test_failure_leaves_no_output(tmp_path, monkeypatch):
    import uavcal_jax.sim.simulate as sim

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(sim.imu_synth, "ground_truth_from_trajectory", boom)
    with pytest.raises(RuntimeError, match="boom"):
        simulate(SimConfig(duration=0.5, frames=False), tmp_path / "rec", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_scale_calibration_keeps_field_of_view():
    full = euroc_calibration(0)
    half = scale_calibration(full, (376, 240))
    assert half.resolution == (376, 240)
    # The image corners see the same directions.
    for (u, v), (uh, vh) in [((-0.5, -0.5), (-0.5, -0.5)), ((751.5, 479.5), (375.5, 239.5))]:
        a = (np.array([u, v]) - full.intrinsics[2:]) / full.intrinsics[:2]
        b = (np.array([uh, vh]) - half.intrinsics[2:]) / half.intrinsics[:2]
        np.testing.assert_allclose(a, b, atol=1e-12)
