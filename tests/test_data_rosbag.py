"""ROS 1 / ROS 2 bags written with rosbags' own writers, read back with read_rosbag."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from uavcal_jax.data.rosbag import read_rosbag
from uavcal_jax.data.sequence import CameraCalibration, ImuCalibration
from uavcal_jax.errors import DataError, DataRepairWarning
from uavcal_jax.imu.noise import ImuNoise

rosbags = pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

T0 = 1_700_000_000_123_456_789
W, H = 16, 12


def _images(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(n, H, W, 3), dtype=np.uint8)


def _imu_values(n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 6))


def write_bag(path: Path, version: int, *, n_imu: int = 50, n_img: int = 6,
              encodings=("mono8", "rgb8", "bgr8"), imu: bool = True, camera_info: bool = False,
              imu_stamps=None, extra_pad: int = 0, imu_values=None) -> dict:
    """A small bag: /imu0 at 200 Hz, one image topic per encoding at 20 Hz."""
    ros1 = version == 1
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]

    def header(t_ns: int, frame: str):
        stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
    imgs = _images(n_img)
    vals = _imu_values(n_imu) if imu_values is None else imu_values
    t_imu = T0 + np.arange(n_imu, dtype=np.int64) * 5_000_000 if imu_stamps is None \
        else np.asarray(imu_stamps, np.int64)
    t_img = T0 + np.arange(n_img, dtype=np.int64) * 50_000_000
    Vector3, Quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    with writer:
        if imu:
            c_imu = writer.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=ts)
            for k_msg, (t, v) in enumerate(zip(t_imu, vals, strict=True)):
                msg = T["sensor_msgs/msg/Imu"](
                    header=header(int(t), "imu"),
                    orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=Vector3(x=v[0], y=v[1], z=v[2]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vector3(x=v[3], y=v[4], z=v[5]),
                    linear_acceleration_covariance=np.zeros(9))
                # received in write order, 1 ms after the nominal stamp
                writer.write(c_imu, T0 + k_msg * 5_000_000 + 1_000_000,
                             serialize(msg, "sensor_msgs/msg/Imu"))
        for k, enc in enumerate(encodings):
            c = writer.add_connection(f"/cam{k}/image_raw", "sensor_msgs/msg/Image", typestore=ts)
            if camera_info:
                ci = writer.add_connection(f"/cam{k}/camera_info", "sensor_msgs/msg/CameraInfo",
                                           typestore=ts)
                kw = dict(D=np.array([0.1, -0.2, 0.001, 0.002, 0.0]),
                          K=np.array([100.0, 0, 8, 0, 101.0, 6, 0, 0, 1]),
                          R=np.eye(3).ravel(), P=np.zeros(12))
                if not ros1:
                    kw = {key.lower(): value for key, value in kw.items()}
                info = T["sensor_msgs/msg/CameraInfo"](
                    header=header(int(t_img[0]), "cam"), height=H, width=W,
                    distortion_model="plumb_bob", binning_x=0, binning_y=0,
                    roi=T["sensor_msgs/msg/RegionOfInterest"](
                        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False), **kw)
                writer.write(ci, int(t_img[0]), serialize(info, "sensor_msgs/msg/CameraInfo"))
            for t, rgb in zip(t_img, imgs, strict=True):
                if enc == "mono8":
                    px = rgb[..., 0]
                elif enc == "rgb8":
                    px = rgb
                else:
                    px = rgb[..., ::-1]
                ch = 1 if px.ndim == 2 else 3
                step = W * ch + extra_pad
                buf = np.zeros((H, step), np.uint8)
                buf[:, : W * ch] = px.reshape(H, W * ch)
                msg = T["sensor_msgs/msg/Image"](
                    header=header(int(t), f"cam{k}"), height=H, width=W, encoding=enc,
                    is_bigendian=0, step=step, data=buf.ravel())
                writer.write(c, int(t) + 2_000_000, serialize(msg, "sensor_msgs/msg/Image"))
    return {"t_imu": t_imu, "imu": vals, "t_img": t_img, "images": imgs}


def _bag_path(tmp_path: Path, version: int) -> Path:
    return tmp_path / ("test.bag" if version == 1 else "test_bag2")


@pytest.mark.parametrize("version", [1, 2])
def test_round_trip(tmp_path, version):
    path = _bag_path(tmp_path, version)
    ref = write_bag(path, version, extra_pad=version)  # row padding: step > width * channels
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataRepairWarning)
        seq = read_rosbag(path)
    assert seq.name == ("test" if version == 1 else "test_bag2")
    np.testing.assert_array_equal(seq.imu.t_ns, ref["t_imu"])  # header stamps, exact
    np.testing.assert_array_equal(seq.imu.gyro, ref["imu"][:, :3])
    np.testing.assert_array_equal(seq.imu.accel, ref["imu"][:, 3:])
    assert sorted(seq.cameras) == ["cam0", "cam1", "cam2"]
    imgs = ref["images"]
    for name in ("cam0", "cam1", "cam2"):
        cam = seq.cameras[name]
        np.testing.assert_array_equal(cam.t_ns, ref["t_img"])
        assert cam.calibration.resolution == (W, H)
        assert cam.calibration.rate_hz == pytest.approx(20.0)
        assert np.all(np.isnan(cam.calibration.intrinsics))
    for i in range(len(imgs)):
        # mono8
        np.testing.assert_array_equal(seq.cameras["cam0"].load(i), imgs[i, ..., 0])
        rgb = seq.cameras["cam0"].load(i, "rgb")
        assert rgb.shape == (H, W, 3) and all(np.array_equal(rgb[..., c], imgs[i, ..., 0])
                                              for c in range(3))
        # rgb8 and bgr8 both come back as the same RGB image
        for name in ("cam1", "cam2"):
            got = seq.cameras[name].load(i, "rgb")
            assert got.dtype == np.uint8
            np.testing.assert_array_equal(got, imgs[i])
            gray = seq.cameras[name].load(i, "gray")
            np.testing.assert_array_equal(
                gray, __import__("cv2").cvtColor(imgs[i], __import__("cv2").COLOR_RGB2GRAY))
    assert seq.imu_calibration is None and seq.ground_truth is None


@pytest.mark.parametrize("version", [1, 2])
def test_explicit_topics_and_calibration(tmp_path, version):
    path = _bag_path(tmp_path, version)
    write_bag(path, version)
    cal = CameraCalibration(np.array([10.0, 11, 8, 6]), np.zeros(4), (W, H), 20.0, np.eye(4))
    imu_cal = ImuCalibration(200.0, np.eye(4), ImuNoise(gyro_noise_density=1e-4,
                                                        gyro_random_walk=1e-5,
                                                        accel_noise_density=1e-3,
                                                        accel_random_walk=1e-4))
    seq = read_rosbag(path, imu_topic="/imu0", image_topics={"left": "/cam2/image_raw"},
                      calibration={"left": cal, "imu": imu_cal})
    assert list(seq.cameras) == ["left"]
    assert seq.cameras["left"].calibration is cal
    assert seq.imu_calibration is imu_cal
    seq = read_rosbag(path, image_topics=["/cam1/image_raw"])
    assert list(seq.cameras) == ["cam0"]
    with pytest.raises(DataError, match="no topic"):
        read_rosbag(path, imu_topic="/nope")
    with pytest.raises(DataError, match="not sensor_msgs/msg/Image"):
        read_rosbag(path, image_topics=["/imu0"])
    bad = CameraCalibration(np.array([10.0, 11, 8, 6]), np.zeros(4), (W + 1, H), 20.0, np.eye(4))
    with pytest.raises(DataError, match="calibration says"):
        read_rosbag(path, calibration={"cam0": bad})


@pytest.mark.parametrize("version", [1, 2])
def test_camera_info_calibration(tmp_path, version):
    path = _bag_path(tmp_path, version)
    write_bag(path, version, camera_info=True, encodings=("mono8",))
    seq = read_rosbag(path)
    cal = seq.cameras["cam0"].calibration
    np.testing.assert_array_equal(cal.intrinsics, [100.0, 101.0, 8.0, 6.0])
    np.testing.assert_array_equal(cal.distortion, [0.1, -0.2, 0.001, 0.002])


@pytest.mark.parametrize("version", [1, 2])
def test_no_imu_topic(tmp_path, version):
    path = _bag_path(tmp_path, version)
    write_bag(path, version, imu=False)
    with pytest.raises(DataError, match="no sensor_msgs/msg/Imu topic") as err:
        read_rosbag(path)
    assert err.value.path == path


def test_missing_and_corrupt_bag(tmp_path):
    with pytest.raises(DataError, match="no such bag"):
        read_rosbag(tmp_path / "missing.bag")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\nthis is not a bag")
    with pytest.raises(DataError, match="cannot open bag") as err:
        read_rosbag(junk)
    assert err.value.path == junk
    (tmp_path / "notabag").mkdir()
    with pytest.raises(DataError, match="metadata.yaml"):
        read_rosbag(tmp_path / "notabag")


@pytest.mark.parametrize("version", [1, 2])
def test_imu_policy(tmp_path, version):
    n = 60
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    t = np.delete(t, np.arange(30, 36))  # a 35 ms gap
    vals = _imu_values(len(t))
    vals[5, 2] = np.nan
    path = _bag_path(tmp_path, version)
    write_bag(path, version, imu_stamps=t, imu_values=vals, encodings=())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = read_rosbag(path)
    msgs = [str(w.message) for w in caught if issubclass(w.category, DataRepairWarning)]
    assert len(seq.imu) == len(t) - 1
    assert any("NaN/inf" in m for m in msgs)
    assert any("IMU gaps" in m and "35.0 ms" in m for m in msgs)
    with pytest.raises(DataError):
        read_rosbag(path, strict=True)


@pytest.mark.parametrize("version", [1, 2])
def test_out_of_order_and_duplicates(tmp_path, version):
    t = T0 + np.arange(20, dtype=np.int64) * 5_000_000
    t[[4, 5]] = t[[5, 4]]  # stamps out of receive order
    vals = _imu_values(20)
    path = _bag_path(tmp_path, version)
    write_bag(path, version, imu_stamps=t, imu_values=vals, encodings=())
    with pytest.warns(DataRepairWarning, match="out of order"):
        seq = read_rosbag(path)
    assert np.all(np.diff(seq.imu.t_ns) > 0)
    np.testing.assert_array_equal(seq.imu.gyro[4], vals[5, :3])
    # A repeated stamp with other values is an error; with the same values it is dropped.
    t2 = T0 + np.arange(20, dtype=np.int64) * 5_000_000
    t2[7] = t2[6]
    path2 = tmp_path / ("dup.bag" if version == 1 else "dup2")
    write_bag(path2, version, imu_stamps=t2, imu_values=vals, encodings=())
    with pytest.raises(DataError, match="different contents"):
        read_rosbag(path2)
    vals[7] = vals[6]
    path3 = tmp_path / ("dup3.bag" if version == 1 else "dup3")
    write_bag(path3, version, imu_stamps=t2, imu_values=vals, encodings=())
    with pytest.warns(DataRepairWarning, match="duplicated"):
        assert len(read_rosbag(path3).imu) == 19
