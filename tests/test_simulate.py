"""The simulator's output: EuRoC ASL writer and the orchestration of ``simulate``."""

from __future__ import annotations

import dataclasses
import re
import warnings

import cv2
import numpy as np
import pytest

from uavcal_jax.data import (
    camera_calibration_from_yaml,
    imu_calibration_from_yaml,
    read_euroc,
    read_sensor_yaml,
)
from uavcal_jax.data.sequence import CameraCalibration, GroundTruth, ImuCalibration, ImuData
from uavcal_jax.data.targets import TargetLabels
from uavcal_jax.errors import DataError, DataRepairWarning
from uavcal_jax.geometry.camera import euroc_calibration
from uavcal_jax.sim.writer import (
    GROUND_TRUTH_HEADER,
    IMU_HEADER,
    EurocWriter,
    camera_sensor_yaml,
    depth_to_millimetres,
    ground_truth_sensor_yaml,
    imu_sensor_yaml,
)

EUROC_IMU = ImuCalibration(rate_hz=200.0, T_BS=np.eye(4), gyroscope_noise_density=1.6968e-04,
                           gyroscope_random_walk=1.9393e-05,
                           accelerometer_noise_density=2.0e-3, accelerometer_random_walk=3.0e-3)


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
    assert seq.imu_calibration.gyroscope_noise_density == EUROC_IMU.gyroscope_noise_density
    assert seq.imu_calibration.accelerometer_random_walk == EUROC_IMU.accelerometer_random_walk
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
