"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``) bags via ``rosbags``.

:func:`read_rosbag` reads ``sensor_msgs/msg/Imu`` and ``sensor_msgs/msg/Image`` topics into a
:class:`~uavcal_jax.data.sequence.Sequence`:

* Topics are found by message type when not given: the one ``Imu`` topic (several: pass
  ``imu_topic``), and every ``Image`` topic, in sorted topic order, named ``cam0``, ``cam1``...
  (``image_topics`` may be a list -- named the same way -- or a ``{name: topic}`` dict).
* Times are the messages' ``header.stamp`` (sensor time), not the bag's receive time; a zero
  stamp falls back to the receive time.
* Frames are decoded lazily: the reader keeps each image message's raw serialized bytes and
  deserializes + converts on ``load(i, color)``. Encodings ``mono8``, ``rgb8``, ``bgr8``
  (and ``8UC1``, ``8UC3`` = BGR, ``rgba8``, ``bgra8``); others are a ``DataError`` at read
  time. ``CompressedImage`` topics are not read.
* Calibration: ``calibration`` may be a :class:`Sequence` (e.g. ``read_euroc`` of the same rig:
  its cameras' calibrations by name and its IMU calibration are used) or a dict
  ``{"cam0": CameraCalibration, ..., "imu": ImuCalibration}``. Without one, a camera's
  ``sensor_msgs/msg/CameraInfo`` in the same namespace (``/cam0/image_raw`` ->
  ``/cam0/camera_info``) gives intrinsics (``K``) and ``plumb_bob`` distortion; otherwise the
  intrinsics are **NaN** (unknown), distortion zero, ``T_BS`` identity, resolution from the
  first image and ``rate_hz`` measured. ``imu_calibration`` is ``None`` unless given.

Bad-input policy (``DataError`` names the bag; warnings are ``DataRepairWarning``;
``strict=True`` turns every repair into an error): missing bag, unreadable bag, no ``Imu``
topic, an unknown topic name, an undecodable message, an unsupported encoding or an image
whose byte count disagrees with ``height * step`` are errors. Messages out of order by header
stamp are sorted (warning); repeated stamps with identical contents are dropped (warning),
with different contents they are an error; IMU messages with NaN/inf are dropped (warning);
gaps (IMU > 3 periods, camera > 1.5 periods) are warned about.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uavcal_jax.data.sequence import (
    CameraCalibration,
    FrameStream,
    ImuCalibration,
    ImuData,
    Sequence,
)
from uavcal_jax.data.timing import (
    CAMERA_GAP_FACTOR,
    IMU_GAP_FACTOR,
    describe_gaps,
    find_gaps,
    measured_rate_hz,
    nominal_period_ns,
)
from uavcal_jax.errors import DataError, DataRepairWarning

IMU_TYPE = "sensor_msgs/msg/Imu"
IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"

#: encoding -> (channels, cv2 conversion to gray, cv2 conversion to RGB or None for as-is)
_ENCODINGS: dict[str, tuple[int, int | None, int | None]] = {
    "mono8": (1, None, cv2.COLOR_GRAY2RGB),
    "8UC1": (1, None, cv2.COLOR_GRAY2RGB),
    "rgb8": (3, cv2.COLOR_RGB2GRAY, None),
    "bgr8": (3, cv2.COLOR_BGR2GRAY, cv2.COLOR_BGR2RGB),
    "8UC3": (3, cv2.COLOR_BGR2GRAY, cv2.COLOR_BGR2RGB),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2RGB),
}


def _warn(message: str, path: Path, strict: bool) -> None:
    if strict:
        raise DataError(f"{message} (strict mode: not repaired)", path)
    warnings.warn(f"{path}: {message}", DataRepairWarning, stacklevel=4)


def _stamp_ns(msg: Any, receive_ns: int) -> int:
    stamp = msg.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else int(receive_ns)


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as err:  # rosbags raises several unrelated error types here
        raise DataError(f"cannot open bag: {err}", path) from None
    return reader


#: A ROS 1 bag file's suffix, and the storage files of a ROS 2 bag (whose folder, holding
#: :data:`ROS2_METADATA`, is the bag).
ROS1_SUFFIX = ".bag"
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")
ROS2_METADATA = "metadata.yaml"


def is_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml``) or its storage file."""
    path = Path(path)
    if path.is_file():
        return path.suffix in (ROS1_SUFFIX, *ROS2_STORAGE_SUFFIXES)
    return path.is_dir() and (path / ROS2_METADATA).is_file()


def _bag_path(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise DataError("no such bag", path)
    # A ROS 2 storage file (.db3 / .mcap) given directly: its folder is the bag.
    if path.is_file() and path.suffix in ROS2_STORAGE_SUFFIXES and (
            path.parent / ROS2_METADATA).is_file():
        return path.parent
    if path.is_dir() and not (path / ROS2_METADATA).is_file():
        raise DataError("not a ROS 2 bag folder: no metadata.yaml", path / ROS2_METADATA)
    return path


def _order(t_ns: np.ndarray, payload: list, what: str, path: Path, strict: bool,
           same=None) -> np.ndarray:
    """Indices that sort by stamp and drop identical duplicates (see module docstring)."""
    n = t_ns.shape[0]
    order = np.argsort(t_ns, kind="stable")
    if np.any(order != np.arange(n)):
        moved = int(np.sum(order != np.arange(n)))
        _warn(f"{what}: {moved} messages out of order by header stamp; sorted", path, strict)
    ts = t_ns[order]
    dup = np.flatnonzero(np.diff(ts) == 0) + 1
    drop = []
    for k in dup:
        a, b = payload[order[k - 1]], payload[order[k]]
        if same(a, b) if same else a == b:
            drop.append(k)
        else:
            raise DataError(f"{what}: two messages with header stamp {int(ts[k])} and "
                            "different contents", path)
    if drop:
        _warn(f"{what}: dropped {len(drop)} duplicated messages (same stamp and contents)",
              path, strict)
        order = np.delete(order, drop)
    return order


def _resolve_topics(topics: Mapping[str, Any], imu_topic, image_topics, path: Path):
    by_type: dict[str, list[str]] = {}
    for name, info in topics.items():
        by_type.setdefault(info.msgtype, []).append(name)
    if imu_topic is None:
        imus = sorted(by_type.get(IMU_TYPE, []))
        if not imus:
            have = ", ".join(f"{t} ({topics[t].msgtype})" for t in sorted(topics)) or "none"
            raise DataError(f"no {IMU_TYPE} topic in the bag (topics: {have})", path)
        if len(imus) > 1:
            raise DataError(f"several IMU topics {imus}: pass imu_topic", path)
        imu_topic = imus[0]
    if imu_topic not in topics:
        raise DataError(f"no topic {imu_topic!r} in the bag (have {sorted(topics)})", path)
    if topics[imu_topic].msgtype != IMU_TYPE:
        raise DataError(f"topic {imu_topic!r} is {topics[imu_topic].msgtype}, not {IMU_TYPE}",
                        path)
    if image_topics is None:
        image_topics = sorted(by_type.get(IMAGE_TYPE, []))
    if not isinstance(image_topics, Mapping):
        image_topics = {f"cam{i}": t for i, t in enumerate(image_topics)}
    for topic in image_topics.values():
        if topic not in topics:
            raise DataError(f"no topic {topic!r} in the bag (have {sorted(topics)})", path)
        if topics[topic].msgtype != IMAGE_TYPE:
            raise DataError(f"topic {topic!r} is {topics[topic].msgtype}, not {IMAGE_TYPE}",
                            path)
    infos = {}
    for topic in by_type.get(CAMERA_INFO_TYPE, []):
        infos[topic.rsplit("/", 1)[0]] = topic
    return imu_topic, dict(image_topics), infos


def _decode(msg: Any, color: str, where: str) -> np.ndarray:
    enc = str(msg.encoding)
    if enc not in _ENCODINGS:
        raise DataError(f"unsupported image encoding {enc!r} (supported: {sorted(_ENCODINGS)})",
                        where)
    ch, to_gray, to_rgb = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * ch or data.size != h * step:
        raise DataError(f"image data has {data.size} bytes, expected height*step = {h}*{step} "
                        f"(width {w}, {ch} channels)", where)
    img = data.reshape(h, step)[:, : w * ch].reshape((h, w) if ch == 1 else (h, w, ch))
    if color == "gray":
        out = img if to_gray is None else cv2.cvtColor(img, to_gray)
    else:
        out = img if to_rgb is None else cv2.cvtColor(img, to_rgb)
    return np.ascontiguousarray(out)


def _camera_info_calibration(msg: Any, rate_hz: float) -> CameraCalibration:
    K = np.asarray(getattr(msg, "K", getattr(msg, "k", None)), dtype=np.float64).reshape(3, 3)
    D = np.asarray(getattr(msg, "D", getattr(msg, "d", [])), dtype=np.float64).ravel()
    dist = np.zeros(4)
    if str(msg.distortion_model) in ("plumb_bob", "rational_polynomial", "radial-tangential"):
        dist[: min(4, D.size)] = D[:4]
    return CameraCalibration(
        intrinsics=np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), distortion=dist,
        resolution=(int(msg.width), int(msg.height)), rate_hz=rate_hz, T_BS=np.eye(4),
        distortion_model="radial-tangential")


def read_rosbag(path: str | Path, imu_topic: str | None = None,
                image_topics: list[str] | Mapping[str, str] | None = None,
                calibration: Sequence | Mapping[str, Any] | None = None, *,
                strict: bool = False) -> Sequence:
    """Read a ROS 1 or ROS 2 bag; see the module docstring for topics, times and policy."""
    path = _bag_path(path)
    reader = _open_reader(path)
    try:
        imu_topic, image_topics, info_topics = _resolve_topics(
            reader.topics, imu_topic, image_topics, path)
        typestore = reader.typestore
        deser = typestore.deserialize_cdr if reader.is2 else typestore.deserialize_ros1
        wanted = {imu_topic, *image_topics.values(), *info_topics.values()}
        conns = [c for c in reader.connections if c.topic in wanted]
        imu_rows: list[tuple[int, tuple[float, ...]]] = []
        frames: dict[str, list[tuple[int, bytes, str]]] = {t: [] for t in image_topics.values()}
        first_info: dict[str, Any] = {}
        for conn, receive_ns, raw in reader.messages(connections=conns):
            topic = conn.topic
            try:
                if topic == imu_topic:
                    m = deser(raw, IMU_TYPE)
                    w, a = m.angular_velocity, m.linear_acceleration
                    imu_rows.append((_stamp_ns(m, receive_ns),
                                     (w.x, w.y, w.z, a.x, a.y, a.z)))
                elif topic in frames:
                    m = deser(raw, IMAGE_TYPE)
                    if str(m.encoding) not in _ENCODINGS:
                        raise DataError(f"topic {topic!r}: unsupported image encoding "
                                        f"{m.encoding!r} (supported: {sorted(_ENCODINGS)})",
                                        path)
                    frames[topic].append((_stamp_ns(m, receive_ns), bytes(raw),
                                          f"{int(m.width)}x{int(m.height)}"))
                elif topic not in first_info:
                    first_info[topic] = deser(raw, CAMERA_INFO_TYPE)
            except DataError:
                raise
            except Exception as err:
                raise DataError(f"topic {topic!r}: cannot decode message at "
                                f"{receive_ns} ns: {err}", path) from None
    finally:
        reader.close()

    # IMU
    if not imu_rows:
        raise DataError(f"IMU topic {imu_topic!r} has no messages", path)
    t_imu = np.array([r[0] for r in imu_rows], dtype=np.int64)
    vals = np.array([r[1] for r in imu_rows], dtype=np.float64)
    order = _order(t_imu, [tuple(v) for v in vals], f"IMU topic {imu_topic}", path, strict)
    t_imu, vals = t_imu[order], vals[order]
    finite = np.all(np.isfinite(vals), axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        _warn(f"IMU topic {imu_topic}: dropped {bad.size} messages with NaN/inf values "
              f"(stamps {', '.join(str(int(t)) for t in t_imu[bad][:10])})", path, strict)
        t_imu, vals = t_imu[finite], vals[finite]

    imu_calib = None
    cam_calibs: dict[str, CameraCalibration] = {}
    if isinstance(calibration, Sequence):
        imu_calib = calibration.imu_calibration
        cam_calibs = {k: s.calibration for k, s in calibration.cameras.items()}
    elif calibration is not None:
        for key, value in calibration.items():
            if isinstance(value, ImuCalibration):
                imu_calib = value
            elif isinstance(value, CameraCalibration):
                cam_calibs[key] = value
            else:
                raise TypeError(f"calibration[{key!r}] must be a CameraCalibration or "
                                f"ImuCalibration, got {type(value).__name__}")
    period = nominal_period_ns(imu_calib.rate_hz if imu_calib else None, t_imu)
    gaps = find_gaps(t_imu, period, IMU_GAP_FACTOR)
    if gaps:
        _warn(f"IMU topic {imu_topic}: {len(gaps)} IMU gaps longer than {IMU_GAP_FACTOR:g} "
              f"sample periods: {describe_gaps(gaps)}", path, strict)
    imu = ImuData(t_ns=t_imu, gyro=np.ascontiguousarray(vals[:, :3]),
                  accel=np.ascontiguousarray(vals[:, 3:]))

    # Cameras
    cameras: dict[str, FrameStream] = {}
    for name, topic in image_topics.items():
        msgs = frames[topic]
        t_cam = np.array([m[0] for m in msgs], dtype=np.int64)
        order = _order(t_cam, [m[1] for m in msgs], f"image topic {topic}", path, strict)
        msgs = [msgs[k] for k in order]
        t_cam = t_cam[order]
        sizes = {m[2] for m in msgs}
        if len(sizes) > 1:
            raise DataError(f"image topic {topic}: images of several sizes {sorted(sizes)}", path)
        rate = measured_rate_hz(t_cam) or float("nan")
        calib = cam_calibs.get(name)
        if calib is None and topic.rsplit("/", 1)[0] in info_topics:
            info = first_info.get(info_topics[topic.rsplit("/", 1)[0]])
            if info is not None:
                calib = _camera_info_calibration(info, rate)
        if calib is None:
            w, h = (int(x) for x in sizes.pop().split("x")) if sizes else (0, 0)
            calib = CameraCalibration(intrinsics=np.full(4, np.nan), distortion=np.zeros(4),
                                      resolution=(w, h), rate_hz=rate, T_BS=np.eye(4),
                                      camera_model="unknown")
        elif sizes:
            w, h = (int(x) for x in next(iter(sizes)).split("x"))
            if (w, h) != tuple(calib.resolution):
                raise DataError(f"image topic {topic}: images are {w}x{h} but the calibration "
                                f"says {calib.resolution[0]}x{calib.resolution[1]}", path)
        if not np.isfinite(calib.rate_hz) and np.isfinite(rate):
            calib = replace(calib, rate_hz=rate)
        gaps = find_gaps(t_cam, nominal_period_ns(calib.rate_hz, t_cam), CAMERA_GAP_FACTOR)
        if gaps:
            _warn(f"image topic {topic}: {len(gaps)} gaps longer than {CAMERA_GAP_FACTOR} frame "
                  f"periods (dropped frames): {describe_gaps(gaps)}", path, strict)
        raws = [m[1] for m in msgs]
        where = f"{path} [{topic}]"

        def loader(i: int, color: str = "gray", _raws=raws, _where=where, _t=t_cam) -> np.ndarray:
            try:
                msg = deser(_raws[i], IMAGE_TYPE)
            except Exception as err:
                raise DataError(f"cannot decode image message {i}: {err}", _where) from None
            return _decode(msg, color, f"{_where} frame {i} (stamp {int(_t[i])})")

        cameras[name] = FrameStream(name=name, t_ns=t_cam, paths=(), calibration=calib,
                                    loader=loader)

    return Sequence(name=path.stem if path.is_file() else path.name, root=path, cameras=cameras,
                    imu=imu, imu_calibration=imu_calib, ground_truth=None)
