"""EuRoC / ASL folder reader (``mav0/cam0``, ``imu0``, ``state_groundtruth_estimate0`` ...).

:func:`read_euroc` reads a recording in the ASL layout (the EuRoC MAV data set, Kalibr, and
this project's simulator; names and headers in :mod:`uavcal_jax.data.euroc_format`, the writer
is :mod:`uavcal_jax.data.euroc_writer`) into a :class:`~uavcal_jax.data.sequence.Sequence`:

* ``camN/`` (every ``cam<digits>`` folder): ``data.csv`` (``#timestamp [ns],filename``),
  ``data/<file>.png`` and ``sensor.yaml``. Frames are *not* read here; each
  :class:`~uavcal_jax.data.sequence.FrameStream` loads image ``i`` with ``cv2.imread`` when
  asked (``stream.load(i, "gray")`` -> (H, W) uint8, ``"rgb"`` -> (H, W, 3) uint8, whatever the
  PNG's own channel count).
* ``depthN/``: the same layout, PNG ``uint16`` in **millimetres** (z-depth in the camera frame
  of ``camN``). ``Sequence.depth["depthN"].load(i)`` returns **float32 metres**, (H, W); a
  stored 0 (no depth) stays 0.0. The ``color`` argument is ignored for depth.
* ``imu0/`` (required): ``data.csv`` with ``t, w_x, w_y, w_z, a_x, a_y, a_z``.
* ``state_groundtruth_estimate0/`` (optional): 17 columns ``t, p xyz, q wxyz, v xyz,
  bg xyz, ba xyz``.
* ``target0/`` (optional): target labels, see :mod:`uavcal_jax.data.targets`.

Calibration is taken verbatim from each ``sensor.yaml`` (which starts with OpenCV's
``%YAML:1.0`` directive; see :mod:`uavcal_jax.data.yaml_io`).

Bad-input policy (``DataError`` names the file, and the 1-based line where there is one;
``DataRepairWarning`` says what was repaired; ``strict=True`` turns every repair into a
``DataError``):

* Missing ``mav0``, ``imu0``, a sensor's ``data.csv``, ``sensor.yaml`` or ``data/`` folder:
  ``DataError`` naming the path.
* A CSV row with the wrong number of fields or an unparsable value: ``DataError`` with file and
  line -- except when it is the **last** data row of the file, which is what a recording cut
  off mid-write leaves behind: that row is dropped with a warning.
* Timestamps going backwards: ``DataError`` (file + line). A repeated timestamp whose row is
  identical to the previous one is dropped with a warning; with different values it is a
  ``DataError``.
* IMU or ground-truth rows with NaN/inf values are dropped with one warning listing the lines.
* IMU gaps longer than 3 nominal periods (``1/rate_hz`` of ``sensor.yaml``): one warning
  listing them. Camera gaps longer than 1.5 nominal periods (dropped frames): one warning.
* Frames listed in ``data.csv`` whose image file is missing are dropped, one warning listing
  them (the real EuRoC micro sequence's ``cam1`` lists 4 frames it does not ship).
* A corrupt or truncated image: ``DataError`` naming the image, raised when it is loaded.
  An image whose size differs from ``sensor.yaml``'s resolution: ``DataError`` naming the image
  and both sizes, when loaded; the first frame's image header is also checked at read time.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.data.image_header import image_size
from uavcal_jax.data.sequence import (
    CameraCalibration,
    FrameStream,
    GroundTruth,
    ImuCalibration,
    ImuData,
    Sequence,
)
from uavcal_jax.data.table import drop_non_finite, ordered, read_table
from uavcal_jax.data.targets import read_target_labels
from uavcal_jax.data.timing import (
    CAMERA_GAP_FACTOR,
    IMU_GAP_FACTOR,
    describe_gaps,
    find_gaps,
    list_lines,
    nominal_period_ns,
    repair,
)
from uavcal_jax.data.yaml_io import (
    IMU_NOISE_KEYS,
    imu_noise_from_yaml,
    matrix_from_yaml,
    read_opencv_yaml,
)
from uavcal_jax.errors import DataError

# --------------------------------------------------------------------------------------------
# sensor.yaml
# --------------------------------------------------------------------------------------------


def read_sensor_yaml(path: str | Path) -> dict[str, Any]:
    """A ``sensor.yaml`` as a dict (``%YAML:1.0`` header handled); ``T_BS`` becomes (4, 4)."""
    path = Path(path)
    data = read_opencv_yaml(path)
    if "T_BS" in data:
        data["T_BS"] = matrix_from_yaml(data["T_BS"], (4, 4), path=path, key="T_BS")
    return data


def _require(data: dict, key: str, path: Path | None) -> Any:
    if key not in data:
        raise DataError(f"missing key {key!r}", path)
    return data[key]


def _floats(data: dict, key: str, n: int, path: Path | None) -> np.ndarray:
    value = _require(data, key, path)
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise DataError(f"{key}: expected {n} numbers, got {value!r}", path) from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise DataError(f"{key}: expected {n} finite numbers, got {data[key]!r}", path)
    return arr


def _number(data: dict, key: str, path: Path | None) -> float:
    value = _require(data, key, path)
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{key}: expected a number, got {value!r}", path) from None
    if not np.isfinite(out):
        raise DataError(f"{key}: expected a finite number, got {value!r}", path)
    return out


def _T_BS(data: dict, path: Path | None) -> np.ndarray:
    T = _require(data, "T_BS", path)
    return matrix_from_yaml(T, (4, 4), path=path, key="T_BS")


def camera_calibration_from_yaml(data: dict[str, Any], path: str | Path | None = None
                                 ) -> CameraCalibration:
    """:class:`CameraCalibration` from a parsed camera (or depth) ``sensor.yaml``."""
    path = None if path is None else Path(path)
    intr = _floats(data, "intrinsics", 4, path)
    dist = _floats(data, "distortion_coefficients", 4, path) if "distortion_coefficients" in data \
        else np.zeros(4)
    res = _floats(data, "resolution", 2, path)
    if np.any(res <= 0) or np.any(res != np.round(res)):
        raise DataError(f"resolution: expected two positive integers, got {data['resolution']}",
                        path)
    return CameraCalibration(
        intrinsics=intr,
        distortion=dist,
        resolution=(int(res[0]), int(res[1])),
        rate_hz=_number(data, "rate_hz", path),
        T_BS=_T_BS(data, path),
        camera_model=str(data.get("camera_model", "pinhole")),
        distortion_model=str(data.get("distortion_model", "radial-tangential")),
    )


def imu_calibration_from_yaml(data: dict[str, Any], path: str | Path | None = None
                              ) -> ImuCalibration:
    """:class:`ImuCalibration` from a parsed IMU ``sensor.yaml``."""
    path = None if path is None else Path(path)
    return ImuCalibration(
        rate_hz=_number(data, "rate_hz", path),
        T_BS=_T_BS(data, path),
        noise=imu_noise_from_yaml({key: _number(data, key, path) for key in IMU_NOISE_KEYS}),
    )


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------


def load_image(path: str | Path, color: str = "gray",
               resolution: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit image as gray (H, W) or RGB (H, W, 3) uint8, checking its size.

    Raises:
        DataError: missing, corrupt or truncated file (``cv2.imread`` returns ``None``), or a
            size other than ``resolution`` ``(width, height)``.
    """
    path = Path(path)
    flag = cv2.IMREAD_GRAYSCALE if color == "gray" else cv2.IMREAD_COLOR
    img = cv2.imread(str(path), flag)
    if img is None:
        what = "missing image" if not path.is_file() else "corrupt or truncated image"
        raise DataError(f"{what} (cv2.imread could not decode it)", path)
    _check_size(img, path, resolution)
    if color == "rgb":
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.dtype != np.uint8:
        raise DataError(f"expected an 8-bit image, got {img.dtype}", path)
    return img


def load_depth(path: str | Path, resolution: tuple[int, int] | None = None) -> np.ndarray:
    """Read a uint16 millimetre depth PNG as float32 metres (H, W); 0 (no depth) stays 0."""
    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        what = "missing depth image" if not path.is_file() else "corrupt or truncated depth image"
        raise DataError(f"{what} (cv2.imread could not decode it)", path)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DataError(f"expected a single-channel uint16 depth PNG (millimetres), got "
                        f"{img.dtype} with shape {img.shape}", path)
    _check_size(img, path, resolution)
    return img.astype(np.float32) * np.float32(fmt.DEPTH_SCALE_M)


def _check_size(img: np.ndarray, path: Path, resolution: tuple[int, int] | None) -> None:
    if resolution is None:
        return
    w, h = img.shape[1], img.shape[0]
    if (w, h) != tuple(resolution):
        raise DataError(
            f"image is {w}x{h} but sensor.yaml says {resolution[0]}x{resolution[1]} "
            "(width x height)", path)


# --------------------------------------------------------------------------------------------
# Folder reader
# --------------------------------------------------------------------------------------------


def find_mav0(root: str | Path) -> Path:
    """``root/mav0``, or ``root`` itself when it is the ``mav0`` folder (or holds ``imu0``)."""
    root = Path(root)
    if not root.exists():
        raise DataError("no such folder", root)
    if not root.is_dir():
        raise DataError("not a folder (expected an EuRoC/ASL folder holding mav0)", root)
    if (root / fmt.MAV0).is_dir():
        return root / fmt.MAV0
    if root.name == fmt.MAV0 or (root / fmt.IMU_FOLDER).is_dir():
        return root
    raise DataError(f"not an EuRoC/ASL folder: no {fmt.MAV0} sub-folder", root / fmt.MAV0)


def sensor_folders(mav0: Path, pattern: re.Pattern) -> list[Path]:
    """Sub-folders whose name matches ``pattern``, numerically ordered (cam0, cam1, cam10)."""
    found = [p for p in mav0.iterdir() if p.is_dir() and pattern.match(p.name)]
    return sorted(found, key=lambda p: int(re.sub(r"\D", "", p.name)))


def _read_image_stream(folder: Path, *, depth: bool, strict: bool) -> FrameStream:
    """One ``camN`` / ``depthN`` folder as a lazily loaded stream."""
    yaml_path = folder / fmt.SENSOR_YAML
    calib = camera_calibration_from_yaml(read_sensor_yaml(yaml_path), yaml_path)
    table = read_table(folder / fmt.DATA_CSV, fmt.IMAGE_FIELDS, numeric=False, strict=strict)
    table = ordered(table, strict=strict)
    data_dir = folder / fmt.IMAGE_FOLDER
    if not data_dir.is_dir():
        raise DataError("missing image folder", data_dir)

    present = set(os.listdir(data_dir))
    names = [str(v) for v in table.values[:, 0]]
    missing = [k for k, name in enumerate(names) if name not in present]
    if missing:
        repair(f"dropped {len(missing)} frames listed in data.csv whose image file is missing "
               f"({list_lines(table.lines[missing])}: "
               f"{', '.join(names[k] for k in missing[:10])}{' ...' if len(missing) > 10 else ''})",
               table.path, strict=strict, stacklevel=4)
        keep = np.setdiff1d(np.arange(len(table)), missing)
        table = table.take(keep)
        names = [names[k] for k in keep]

    period = nominal_period_ns(calib.rate_hz, table.t_ns)
    gaps = find_gaps(table.t_ns, period, CAMERA_GAP_FACTOR)
    if gaps:
        repair(f"{len(gaps)} gaps longer than {CAMERA_GAP_FACTOR} frame periods "
               f"(dropped frames): {describe_gaps(gaps)}", table.path, strict=strict,
               stacklevel=4)

    paths = tuple(data_dir / name for name in names)
    if paths:
        try:
            size = image_size(paths[0])
        except DataError:
            size = None  # a corrupt image is reported when it is loaded (module docstring)
        if size is not None and size != calib.resolution:
            raise DataError(
                f"image is {size[0]}x{size[1]} but sensor.yaml says "
                f"{calib.resolution[0]}x{calib.resolution[1]} (width x height)", paths[0])

    resolution = calib.resolution
    loader: Callable[[int, str], np.ndarray]
    if depth:
        def loader(i: int, color: str = "gray") -> np.ndarray:
            return load_depth(paths[i], resolution)
    else:
        def loader(i: int, color: str = "gray") -> np.ndarray:
            return load_image(paths[i], color, resolution)

    return FrameStream(name=folder.name, t_ns=table.t_ns.copy(), paths=paths,
                       calibration=calib, loader=loader)


def read_imu_folder(folder: Path, *, strict: bool = False
                    ) -> tuple[ImuData, ImuCalibration]:
    """``imu0``: samples (after the bad-input policy) and calibration."""
    if not folder.is_dir():
        raise DataError("missing IMU folder", folder)
    yaml_path = folder / fmt.SENSOR_YAML
    calib = imu_calibration_from_yaml(read_sensor_yaml(yaml_path), yaml_path)
    table = read_table(folder / fmt.DATA_CSV, fmt.IMU_FIELDS, strict=strict)
    table = ordered(table, strict=strict)
    table = drop_non_finite(table, strict=strict, what="IMU samples")
    gaps = find_gaps(table.t_ns, nominal_period_ns(calib.rate_hz, table.t_ns), IMU_GAP_FACTOR)
    if gaps:
        repair(f"{len(gaps)} IMU gaps longer than {IMU_GAP_FACTOR:g} sample periods: "
               f"{describe_gaps(gaps)}", table.path, strict=strict, stacklevel=4)
    imu = ImuData(t_ns=table.t_ns, gyro=np.ascontiguousarray(table.values[:, 0:3]),
                  accel=np.ascontiguousarray(table.values[:, 3:6]))
    return imu, calib


def read_ground_truth_csv(path: str | Path, *, strict: bool = False) -> GroundTruth:
    """EuRoC ``state_groundtruth_estimate0/data.csv`` (17 columns) as :class:`GroundTruth`."""
    table = read_table(path, fmt.GROUND_TRUTH_FIELDS, strict=strict)
    table = ordered(table, strict=strict)
    table = drop_non_finite(table, strict=strict, what="ground-truth states")
    v = table.values
    return GroundTruth(
        t_ns=table.t_ns,
        position=np.ascontiguousarray(v[:, 0:3]),
        quaternion=np.ascontiguousarray(v[:, 3:7]),
        velocity=np.ascontiguousarray(v[:, 7:10]),
        bias_gyro=np.ascontiguousarray(v[:, 10:13]),
        bias_accel=np.ascontiguousarray(v[:, 13:16]),
    )


def sequence_name(root: str | Path) -> str:
    root = Path(root).resolve()
    return root.parent.name if root.name == fmt.MAV0 else root.name


def read_euroc(root: str | Path, *, strict: bool = False) -> Sequence:
    """Read an EuRoC/ASL recording (``root`` holds ``mav0``, or is ``mav0``).

    See the module docstring for the layout and the bad-input policy.

    Args:
        root: the sequence folder, or its ``mav0`` folder.
        strict: raise :class:`~uavcal_jax.errors.DataError` instead of repairing (dropping rows
            or frames) and instead of warning about gaps.

    Returns:
        A :class:`~uavcal_jax.data.sequence.Sequence` with lazily loaded camera (and depth)
        frames, IMU samples, ground truth (``None`` when the folder is absent), target labels
        (``None`` when ``target0`` is absent) and the calibration of every sensor.
    """
    mav0 = find_mav0(root)
    cameras = {p.name: _read_image_stream(p, depth=False, strict=strict)
               for p in sensor_folders(mav0, fmt.CAMERA_FOLDER)}
    depth = {p.name: _read_image_stream(p, depth=True, strict=strict)
             for p in sensor_folders(mav0, fmt.DEPTH_FOLDER)}
    imu, imu_calib = read_imu_folder(mav0 / fmt.IMU_FOLDER, strict=strict)
    gt_dir = mav0 / fmt.GROUND_TRUTH_FOLDER
    ground_truth = read_ground_truth_csv(gt_dir / fmt.DATA_CSV, strict=strict) \
        if gt_dir.is_dir() else None
    target_dir = mav0 / fmt.TARGET_FOLDER
    targets = read_target_labels(target_dir) if target_dir.is_dir() else None
    return Sequence(
        name=sequence_name(mav0),
        root=Path(root),
        cameras=cameras,
        imu=imu,
        imu_calibration=imu_calib,
        ground_truth=ground_truth,
        depth=depth,
        targets=targets,
    )
