"""EuRoC/ASL reader on the real V1_01 micro sequence, and on small hand-built folders."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from uavcal_jax.data import read_euroc, read_opencv_yaml, read_sensor_yaml
from uavcal_jax.data.table import read_table
from uavcal_jax.data.targets import TargetLabels, write_target_labels
from uavcal_jax.errors import DataRepairWarning

# Literal values copied from the micro sequence's sensor.yaml files.
CAM0_T_BS = [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
             0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
             -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
             0.0, 0.0, 0.0, 1.0]
CAM1_T_BS = [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
             0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
             -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038,
             0.0, 0.0, 0.0, 1.0]


def _read(root, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = read_euroc(root, **kw)
    return seq, [w for w in caught if issubclass(w.category, DataRepairWarning)]


@pytest.mark.realdata
def test_micro_counts(euroc_micro):
    seq, warns = _read(euroc_micro)
    assert seq.name == "euroc_v101_micro"
    assert sorted(seq.cameras) == ["cam0", "cam1"]
    assert len(seq.cameras["cam0"]) == 95
    assert len(seq.cameras["cam1"]) == 95
    np.testing.assert_array_equal(seq.cameras["cam0"].t_ns, seq.cameras["cam1"].t_ns)
    assert len(seq.imu) == 29_120
    assert len(seq.ground_truth) == 2_895
    assert seq.depth == {}
    assert seq.targets is None
    # cam1/data.csv lists 4 frames the micro sequence does not ship: dropped with one warning.
    assert len(warns) == 1
    assert "cam1" in str(warns[0].message) and "1403715278012143104.png" in str(warns[0].message)
    # Reading mav0 directly gives the same sequence.
    seq2, _ = _read(euroc_micro / "mav0")
    assert seq2.name == "euroc_v101_micro"
    np.testing.assert_array_equal(seq2.imu.t_ns, seq.imu.t_ns)


@pytest.mark.realdata
def test_micro_values(euroc_micro):
    seq, _ = _read(euroc_micro)
    cam0 = seq.cameras["cam0"]
    assert cam0.t_ns[0] == 1403715273262142976
    assert cam0.t_ns[-1] == 1403715277962142976
    assert cam0.t_ns.dtype == np.int64
    # First and last IMU rows, copied from imu0/data.csv.
    assert seq.imu.t_ns[0] == 1403715273262142976
    np.testing.assert_array_equal(
        seq.imu.gyro[0], [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824])
    np.testing.assert_array_equal(
        seq.imu.accel[0], [9.0874956666666655, 0.13075533333333333, -3.6938381666666662])
    assert np.all(np.diff(seq.imu.t_ns) > 0)
    gt = seq.ground_truth
    assert gt.t_ns[0] == 1403715273262142976
    np.testing.assert_array_equal(gt.position[0], [0.878895, 2.1834, 0.948427])
    np.testing.assert_array_equal(gt.quaternion[0], [0.069433, -0.824237, -0.106942, -0.551702])
    np.testing.assert_array_equal(gt.velocity[0], [0.00157587, 0.00179383, -0.00231615])
    np.testing.assert_array_equal(gt.bias_gyro[0], [-0.00224703, 0.0215352, 0.0770299])
    np.testing.assert_array_equal(gt.bias_accel[0], [-0.0180115, 0.0659796, 0.0309774])
    np.testing.assert_allclose(np.linalg.norm(gt.quaternion, axis=1), 1.0, atol=1e-5)


@pytest.mark.realdata
def test_micro_calibration_equals_yaml(euroc_micro):
    seq, _ = _read(euroc_micro)
    c0, c1 = seq.cameras["cam0"].calibration, seq.cameras["cam1"].calibration
    np.testing.assert_array_equal(c0.intrinsics, [458.654, 457.296, 367.215, 248.375])
    np.testing.assert_array_equal(
        c0.distortion, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
    np.testing.assert_array_equal(c1.intrinsics, [457.587, 456.134, 379.999, 255.238])
    np.testing.assert_array_equal(
        c1.distortion, [-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05])
    np.testing.assert_array_equal(c0.T_BS, np.reshape(CAM0_T_BS, (4, 4)))
    np.testing.assert_array_equal(c1.T_BS, np.reshape(CAM1_T_BS, (4, 4)))
    for c in (c0, c1):
        assert c.resolution == (752, 480)
        assert c.rate_hz == 20.0
        assert c.camera_model == "pinhole"
        assert c.distortion_model == "radial-tangential"
    imu = seq.imu_calibration
    assert imu.rate_hz == 200.0
    np.testing.assert_array_equal(imu.T_BS, np.eye(4))
    assert imu.noise.gyro_noise_density == 1.6968e-04
    assert imu.noise.gyro_random_walk == 1.9393e-05
    assert imu.noise.accel_noise_density == 2.0000e-3
    assert imu.noise.accel_random_walk == 3.0000e-3


@pytest.mark.realdata
def test_micro_frames_lazy(euroc_micro):
    seq, _ = _read(euroc_micro)
    cam0 = seq.cameras["cam0"]
    gray = cam0.load(0)
    assert gray.shape == (480, 752) and gray.dtype == np.uint8
    ref = cv2.imread(str(euroc_micro / "mav0/cam0/data/1403715273262142976.png"),
                     cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(gray, ref)
    rgb = cam0.load(0, "rgb")
    assert rgb.shape == (480, 752, 3) and rgb.dtype == np.uint8
    for ch in range(3):
        np.testing.assert_array_equal(rgb[..., ch], ref)
    last = seq.cameras["cam1"].load(94)
    assert last.shape == (480, 752)
    with pytest.raises(IndexError):
        cam0.load(95)


@pytest.mark.realdata
def test_sensor_yaml_with_opencv_directive(euroc_micro):
    path = euroc_micro / "mav0/cam0/sensor.yaml"
    assert path.read_text().startswith("%YAML:1.0")
    data = read_sensor_yaml(path)
    assert data["sensor_type"] == "camera"
    assert data["T_BS"].shape == (4, 4)
    assert read_opencv_yaml(euroc_micro / "mav0/body.yaml")["comment"] == "Asctec Firefly MAV"


def test_opencv_matrix_tag(tmp_path):
    path = tmp_path / "calib.yaml"
    path.write_text("%YAML:1.0\n---\nK: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n"
                    "   data: [ 1., 2., 3., 4. ]\nrate_hz: 20\n")
    data = read_opencv_yaml(path)
    assert data["K"]["data"] == [1.0, 2.0, 3.0, 4.0]
    assert data["rate_hz"] == 20


def test_read_table_fast_and_exact(tmp_path):
    rng = np.random.default_rng(0)
    t = 1403715273262142976 + np.arange(30_000, dtype=np.int64) * 5_000_000
    vals = rng.normal(size=(30_000, 6))
    path = tmp_path / "data.csv"
    lines = ["#timestamp [ns],a,b,c,d,e,f"]
    lines += [f"{ti}," + ",".join(repr(float(v)) for v in row)
              for ti, row in zip(t, vals, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    table = read_table(path, 7)
    np.testing.assert_array_equal(table.t_ns, t)
    np.testing.assert_array_equal(table.values, vals)
    assert table.lines[0] == 2 and table.lines[-1] == 30_001


# ---------------------------------------------------------------- a synthetic ASL folder


def _write_sensor_yaml(folder: Path, kind: str, w: int = 32, h: int = 24) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    tbs = ("T_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.1,\n         0.0, 1.0, 0.0, 0.0,"
           "\n         0.0, 0.0, 1.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\n")
    if kind == "imu":
        body = (f"sensor_type: imu\n{tbs}rate_hz: 200\ngyroscope_noise_density: 1.0e-4\n"
                "gyroscope_random_walk: 2.0e-5\naccelerometer_noise_density: 2.0e-3\n"
                "accelerometer_random_walk: 3.0e-3\n")
    else:
        body = (f"sensor_type: {kind}\n{tbs}rate_hz: 20\nresolution: [{w}, {h}]\n"
                "camera_model: pinhole\nintrinsics: [30.0, 30.0, 16.0, 12.0]\n"
                "distortion_model: radial-tangential\n"
                "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")
    (folder / "sensor.yaml").write_text("%YAML:1.0\n" + body)


def make_asl(root: Path, *, n_frames: int = 10, n_imu: int = 100, color: bool = False,
             depth: bool = False, ground_truth: bool = True) -> Path:
    """A tiny valid ASL folder (frames 20 Hz, IMU 200 Hz), returned as ``root``."""
    mav0 = root / "mav0"
    t0 = 1_000_000_000_000_000_000
    for cam in ("cam0", "cam1"):
        _write_sensor_yaml(mav0 / cam, "camera")
        (mav0 / cam / "data").mkdir()
        rows = ["#timestamp [ns],filename"]
        for i in range(n_frames):
            t = t0 + i * 50_000_000
            img = np.full((24, 32, 3) if color else (24, 32), 10 * i, np.uint8)
            if color:
                img[..., 2] = 200  # red in BGR order
            cv2.imwrite(str(mav0 / cam / "data" / f"{t}.png"), img)
            rows.append(f"{t},{t}.png")
        (mav0 / cam / "data.csv").write_text("\n".join(rows) + "\n")
    if depth:
        _write_sensor_yaml(mav0 / "depth0", "depth")
        (mav0 / "depth0" / "data").mkdir()
        rows = ["#timestamp [ns],filename"]
        for i in range(n_frames):
            t = t0 + i * 50_000_000
            d = np.full((24, 32), 1500 + i, np.uint16)
            d[0, 0] = 0
            cv2.imwrite(str(mav0 / "depth0" / "data" / f"{t}.png"), d)
            rows.append(f"{t},{t}.png")
        (mav0 / "depth0" / "data.csv").write_text("\n".join(rows) + "\n")
    _write_sensor_yaml(mav0 / "imu0", "imu")
    rows = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
            "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    for i in range(n_imu):
        t = t0 + i * 5_000_000
        rows.append(f"{t},{0.01 * i},0.02,0.03,0.1,0.2,{9.81 + 0.001 * i}")
    (mav0 / "imu0" / "data.csv").write_text("\n".join(rows) + "\n")
    if ground_truth:
        gt = mav0 / "state_groundtruth_estimate0"
        gt.mkdir()
        rows = ["#timestamp, p_RS_R_x [m], ..."]
        for i in range(n_imu // 10):
            t = t0 + i * 50_000_000
            rows.append(f"{t},{i},0,1,1,0,0,0,0.5,0,0,0.001,0.002,0.003,0.01,0.02,0.03")
        (gt / "data.csv").write_text("\n".join(rows) + "\n")
    return root


def test_synthetic_folder(tmp_path):
    root = make_asl(tmp_path / "seq", color=True, depth=True)
    seq, warns = _read(root)
    assert warns == []
    assert seq.name == "seq"
    assert len(seq.cameras["cam0"]) == 10 and len(seq.imu) == 100 and len(seq.ground_truth) == 10
    rgb = seq.cameras["cam0"].load(3, "rgb")
    assert rgb.shape == (24, 32, 3)
    assert rgb[0, 0, 0] == 200 and rgb[0, 0, 2] == 30  # RGB order
    gray = seq.cameras["cam0"].load(3)
    assert gray.shape == (24, 32) and gray.dtype == np.uint8
    d = seq.depth["depth0"].load(2)
    assert d.dtype == np.float32 and d.shape == (24, 32)
    assert d[0, 0] == 0.0
    assert d[5, 5] == pytest.approx(1.502)
    assert seq.depth["depth0"].calibration.resolution == (32, 24)
    np.testing.assert_array_equal(seq.ground_truth.position[3], [3, 0, 1])
    np.testing.assert_array_equal(seq.imu_calibration.T_BS[0], [1, 0, 0, 0.1])


def test_target_labels_read(tmp_path):
    root = make_asl(tmp_path / "seq")
    labels = TargetLabels(
        t_ns=np.array([1_000_000_000_000_000_000], np.int64), camera=np.array(["cam0"]),
        track_id=np.array([0]), class_id=np.array([1]),
        box=np.array([[1.0, 2.0, 10.0, 12.0]]), visible_pixels=np.array([90]),
        position=np.array([[1.0, 2.0, 3.0]]), class_names=("person", "car"))
    write_target_labels(root / "mav0" / "target0", labels)
    seq, _ = _read(root)
    assert seq.targets is not None and len(seq.targets) == 1
    assert seq.targets.class_names == ("person", "car")


def test_no_ground_truth(tmp_path):
    root = make_asl(tmp_path / "seq", ground_truth=False)
    seq, _ = _read(root)
    assert seq.ground_truth is None


@pytest.mark.realdata
def test_micro_copy_strict_flags_missing_frames(euroc_micro, tmp_path):
    """strict=True turns the cam1 repair of the real data into an error."""
    root = tmp_path / "micro"
    shutil.copytree(euroc_micro / "mav0" / "imu0", root / "mav0" / "imu0")
    shutil.copytree(euroc_micro / "mav0" / "cam1", root / "mav0" / "cam1")
    from uavcal_jax.errors import DataError

    with pytest.raises(DataError, match="cam1"):
        read_euroc(root, strict=True)
