"""Write a recording as an EuRoC ASL folder (``mav0/``), exactly as EuRoC lays it out.

:class:`EurocWriter` writes the layout of :mod:`uavcal_jax.data.euroc_format` (the names and
headers :func:`uavcal_jax.data.euroc.read_euroc` reads); every sensor folder has a
``sensor.yaml`` that starts with OpenCV's ``%YAML:1.0`` directive and follows EuRoC's key order
and comments.

Numbers in CSV and YAML files are written with Python's shortest round-trip ``repr``, so a
reader gets back exactly the float64 values that were written.

PNG frames are encoded on a thread pool (``cv2.imwrite`` releases the GIL), so encoding
overlaps whatever the caller does next (the simulator renders the next batch meanwhile).
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import time
from collections import deque
from pathlib import Path

import cv2
import numpy as np

from uavcal_jax.data import euroc_format as fmt
from uavcal_jax.data.sequence import CameraCalibration, GroundTruth, ImuCalibration, ImuData
from uavcal_jax.data.targets import TargetLabels, write_target_labels
from uavcal_jax.data.yaml_io import imu_noise_to_yaml
from uavcal_jax.errors import DataError

__all__ = [
    "EurocWriter",
    "camera_sensor_yaml",
    "depth_to_millimetres",
    "ground_truth_sensor_yaml",
    "imu_sensor_yaml",
]


def _num(value: float) -> str:
    """A number as EuRoC writes it: ``20`` for integral values, else round-trip ``repr``."""
    value = float(value)
    return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)


def _list(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.asarray(values).ravel()) + "]"


def _t_bs_block(T_BS: np.ndarray) -> str:
    """``T_BS`` as EuRoC writes it: one matrix row per line, signs hanging left."""
    rows = [", ".join(repr(float(v)) for v in row) for row in np.asarray(T_BS, np.float64)]
    lines = [f"  data: [{rows[0]}"]
    lines += [" " * (8 if row.startswith("-") else 9) + row for row in rows[1:]]
    return "T_BS:\n  cols: 4\n  rows: 4\n" + ",\n".join(lines) + "]\n"


def _noise_entry(key: str, value: float, comment: str) -> str:
    """``key: 1.6968e-04     # comment`` with the comment at column 40, as in EuRoC."""
    text = f"{value:.4e}"
    if float(text) != value:
        text = repr(float(value))
    return f"{key}: {text}".ljust(39) + f" {comment}\n"


def camera_sensor_yaml(calib: CameraCalibration, comment: str,
                       sensor_type: str = "camera", notes: str = "") -> str:
    """A camera ``sensor.yaml`` in EuRoC's layout (``sensor_type: depth`` for depth streams).

    ``notes``: extra comment lines (without ``#``) placed after the distortion entry.
    """
    w, h = calib.resolution
    text = (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        f"sensor_type: {sensor_type}\n"
        f"comment: {comment}\n"
        "\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        + _t_bs_block(calib.T_BS)
        + "\n"
        "# Camera specific definitions.\n"
        f"rate_hz: {_num(calib.rate_hz)}\n"
        f"resolution: [{int(w)}, {int(h)}]\n"
        f"camera_model: {calib.camera_model}\n"
        f"intrinsics: {_list(calib.intrinsics)} #fu, fv, cu, cv\n"
        f"distortion_model: {calib.distortion_model}\n"
        f"distortion_coefficients: {_list(calib.distortion)}\n"
    )
    if notes:
        text += "".join(f"# {line}\n" for line in notes.splitlines())
    return text


#: EuRoC's comment after each noise entry of an IMU ``sensor.yaml`` (units and meaning).
_NOISE_COMMENTS = {
    "gyroscope_noise_density": '# [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )',
    "gyroscope_random_walk": "# [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )",
    "accelerometer_noise_density": '# [ m / s^2 / sqrt(Hz) ]   ( accel "white noise" )',
    "accelerometer_random_walk": "# [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )",
}


def imu_sensor_yaml(calib: ImuCalibration, comment: str) -> str:
    """An IMU ``sensor.yaml`` in EuRoC's layout (the noise model under Kalibr's key names)."""
    noise = "".join(_noise_entry(key, value, _NOISE_COMMENTS[key])
                    for key, value in imu_noise_to_yaml(calib.noise).items())
    return (
        "%YAML:1.0\n"
        "#Default imu sensor yaml file\n"
        "sensor_type: imu\n"
        f"comment: {comment}\n"
        "\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        + _t_bs_block(calib.T_BS)
        + f"rate_hz: {_num(calib.rate_hz)}\n"
        "\n"
        "# inertial sensor noise model parameters (static)\n"
        + noise
        + "\n"
    )


def ground_truth_sensor_yaml(comment: str) -> str:
    """The ground-truth ``sensor.yaml`` in EuRoC's layout (identity ``T_BS``)."""
    return (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        "sensor_type: visual-inertial\n"
        f"comment: {comment}\n"
        "\n"
        "# Sensor extrinsics wrt. the body-frame. This is the transformation of the\n"
        "# tracking prima to the body frame.\n"
        + _t_bs_block(np.eye(4))
    )


def depth_to_millimetres(depth_m, xp=np):
    """z-depth in metres -> uint16 millimetres; no hit, non-finite or > 65.535 m -> 0.

    ``xp`` is the array namespace (``numpy`` or ``jax.numpy``), so the simulator can convert on
    the device before the transfer.
    """
    mm = xp.round(depth_m * (1.0 / fmt.DEPTH_SCALE_M))
    ok = xp.isfinite(mm) & (mm > 0) & (mm <= 65535)
    return xp.where(ok, mm, 0).astype(xp.uint16)


def _check_clean(folder: Path) -> None:
    if folder.exists() and any(folder.iterdir()):
        raise DataError("output folder is not empty", folder)


def _csv_rows(t_ns: np.ndarray, values: np.ndarray) -> str:
    t_ns = np.asarray(t_ns, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    return "".join(
        f"{t},{','.join(map(repr, row))}\n" for t, row in zip(t_ns.tolist(), values.tolist(),
                                                             strict=True)
    )


class EurocWriter:
    """Writes one recording into ``root/mav0`` (``root`` is created; ``mav0`` must not exist
    or be empty).

    Typical use::

        with EurocWriter(root) as w:
            w.add_image_stream("cam0", calib0, comment="...")
            w.write_frame("cam0", t_ns, image_uint8)     # encoded on the thread pool
            w.write_imu(imu, imu_calib, comment="...")
            w.write_ground_truth(gt)
        # leaving the block waits for every PNG and writes each stream's data.csv

    Args:
        root: output folder (holds ``mav0``).
        workers: threads encoding PNGs.
        max_pending: frames queued for encoding before :meth:`write_frame` blocks (bounds
            memory when the producer is faster than the encoder).
        body_comment: ``mav0/body.yaml``'s comment.
    """

    def __init__(self, root: str | Path, *, workers: int = 2, max_pending: int = 64,
                 body_comment: str = "uavcal-jax simulated MAV"):
        self.root = Path(root)
        self.mav0 = self.root / fmt.MAV0
        _check_clean(self.mav0)
        self.mav0.mkdir(parents=True, exist_ok=True)
        (self.mav0 / "body.yaml").write_text(f"%YAML:1.0\ncomment: {body_comment}\n")
        self._streams: dict[str, list[int]] = {}
        self._depth: set[str] = set()
        self._pool = cf.ThreadPoolExecutor(max_workers=max(1, workers),
                                           thread_name_prefix="png")
        self._pending: deque[cf.Future] = deque()
        self._max_pending = max(1, max_pending)
        #: Seconds spent encoding PNGs, summed over the encoder threads.
        self.encode_seconds = 0.0

    # -- context manager -------------------------------------------------------------------

    def __enter__(self) -> EurocWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:  # an error upstream: stop encoding, leave the folder to the caller
            self._pool.shutdown(wait=True, cancel_futures=True)

    # -- image streams ---------------------------------------------------------------------

    def add_image_stream(self, name: str, calib: CameraCalibration, *, comment: str,
                         depth: bool = False) -> Path:
        """Create ``mav0/<name>/`` with its ``sensor.yaml`` (``sensor_type: depth`` if depth)."""
        folder = self.mav0 / name
        (folder / fmt.IMAGE_FOLDER).mkdir(parents=True, exist_ok=False)
        notes = ""
        if depth:
            notes = ("Depth: uint16 PNG, z-depth in the camera frame in millimetres "
                     "(0 = no depth).\nSame intrinsics and extrinsics as its camera.")
        (folder / fmt.SENSOR_YAML).write_text(camera_sensor_yaml(
            calib, comment, sensor_type="depth" if depth else "camera", notes=notes))
        self._streams[name] = []
        if depth:
            self._depth.add(name)
        return folder

    def write_frame(self, name: str, t_ns: int, image: np.ndarray) -> cf.Future:
        """Queue ``data/<t_ns>.png`` of stream ``name`` for encoding.

        ``image``: (H, W) uint8 gray, (H, W, 3) uint8 RGB, or (H, W) uint16 millimetres for
        a depth stream. Timestamps must increase within a stream.
        """
        stamps = self._streams[name]
        t_ns = int(t_ns)
        if stamps and t_ns <= stamps[-1]:
            raise ValueError(f"{name}: timestamp {t_ns} not after {stamps[-1]}")
        image = np.asarray(image)
        if name in self._depth:
            if image.dtype != np.uint16 or image.ndim != 2:
                raise ValueError(f"{name}: depth must be (H, W) uint16, got {image.dtype} "
                                 f"{image.shape}")
        else:
            if image.dtype != np.uint8 or image.ndim not in (2, 3):
                raise ValueError(f"{name}: image must be uint8 (H, W) or (H, W, 3), got "
                                 f"{image.dtype} {image.shape}")
            if image.ndim == 3:
                image = image[..., ::-1]  # RGB -> OpenCV's BGR
        stamps.append(t_ns)
        path = self.mav0 / name / fmt.IMAGE_FOLDER / f"{t_ns}.png"
        while len(self._pending) >= self._max_pending:
            self.encode_seconds += self._pending.popleft().result()
        future = self._pool.submit(_imwrite, path, image)
        self._pending.append(future)
        return future

    # -- tables ----------------------------------------------------------------------------

    def write_imu(self, imu: ImuData, calib: ImuCalibration, *, comment: str,
                  name: str = fmt.IMU_FOLDER) -> None:
        """``mav0/imu0``: ``sensor.yaml`` and the 7-column ``data.csv``."""
        folder = self.mav0 / name
        folder.mkdir(exist_ok=False)
        (folder / fmt.SENSOR_YAML).write_text(imu_sensor_yaml(calib, comment))
        values = np.concatenate([imu.gyro, imu.accel], axis=1)
        (folder / fmt.DATA_CSV).write_text(fmt.IMU_HEADER + "\n" + _csv_rows(imu.t_ns, values))

    def write_ground_truth(self, gt: GroundTruth, *, comment: str = (
            "Simulated ground truth: the exact states of the simulated flight (uavcal-jax).")
                           ) -> None:
        """``mav0/state_groundtruth_estimate0``: the 17-column states (missing velocity or
        biases are written as zeros)."""
        folder = self.mav0 / fmt.GROUND_TRUTH_FOLDER
        folder.mkdir(exist_ok=False)
        (folder / fmt.SENSOR_YAML).write_text(ground_truth_sensor_yaml(comment))
        n = len(gt)
        zeros = np.zeros((n, 3))
        values = np.concatenate([
            gt.position, gt.quaternion,
            zeros if gt.velocity is None else gt.velocity,
            zeros if gt.bias_gyro is None else gt.bias_gyro,
            zeros if gt.bias_accel is None else gt.bias_accel,
        ], axis=1)
        (folder / fmt.DATA_CSV).write_text(fmt.GROUND_TRUTH_HEADER + "\n"
                                           + _csv_rows(gt.t_ns, values))

    def write_targets(self, labels: TargetLabels, name: str = fmt.TARGET_FOLDER) -> None:
        """``mav0/target0`` (see :func:`uavcal_jax.data.targets.write_target_labels`)."""
        write_target_labels(self.mav0 / name, labels)

    # -- finish ----------------------------------------------------------------------------

    def wait(self) -> None:
        """Block until every queued PNG is written (re-raises an encoding error)."""
        while self._pending:
            self.encode_seconds += self._pending.popleft().result()

    def close(self) -> None:
        """Wait for the PNGs, then write each image stream's ``data.csv``."""
        try:
            self.wait()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
        for name, stamps in self._streams.items():
            rows = "".join(f"{t},{t}.png\n" for t in stamps)
            (self.mav0 / name / fmt.DATA_CSV).write_text(fmt.IMAGE_HEADER + "\n" + rows)


def _imwrite(path: Path, image: np.ndarray) -> float:
    """Encode one PNG; returns the seconds it took."""
    t0 = time.perf_counter()
    if not cv2.imwrite(os.fspath(path), np.ascontiguousarray(image)):
        raise OSError(f"{path}: cv2.imwrite failed")
    return time.perf_counter() - t0
