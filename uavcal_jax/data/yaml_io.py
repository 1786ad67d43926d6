"""OpenCV-flavoured YAML (EuRoC ``sensor.yaml``) read with PyYAML.

EuRoC / Kalibr ``sensor.yaml`` files start with the OpenCV directive ``%YAML:1.0``, which
PyYAML rejects (a YAML directive is ``%YAML 1.1``, with a space). OpenCV's writers may also tag
matrices ``!!opencv-matrix`` (``{rows, cols, dt, data}``). :func:`read_opencv_yaml` removes the
directive (and a following ``---``), accepts the matrix tag, and returns plain Python values;
:func:`matrix_from_yaml` turns a ``{rows, cols, data}`` mapping (or a flat / nested list) into an
array. Any failure is a :class:`~uavcal_jax.errors.DataError` naming the file.

An IMU ``sensor.yaml`` states its noise model under Kalibr's key names
(``gyroscope_noise_density`` ...); :data:`IMU_NOISE_KEYS` maps them to the fields of
:class:`~uavcal_jax.imu.noise.ImuNoise`, for the readers and the writer alike.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from uavcal_jax.errors import DataError
from uavcal_jax.imu.noise import ImuNoise

#: ``sensor.yaml`` key (Kalibr / EuRoC) -> :class:`ImuNoise` field, in the order EuRoC writes
#: them.
IMU_NOISE_KEYS = {
    "gyroscope_noise_density": "gyro_noise_density",
    "gyroscope_random_walk": "gyro_random_walk",
    "accelerometer_noise_density": "accel_noise_density",
    "accelerometer_random_walk": "accel_random_walk",
}

_DIRECTIVE = re.compile(r"^\s*%YAML[:\s]\s*\d+(\.\d+)?\s*$")


class _OpenCvLoader(yaml.SafeLoader):
    """SafeLoader that also accepts OpenCV's ``!!opencv-matrix`` (and other ``!!opencv-*``) tags."""


def _opencv_mapping(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_OpenCvLoader.add_multi_constructor("tag:yaml.org,2002:opencv-", _opencv_mapping)
_OpenCvLoader.add_multi_constructor("!opencv-", _opencv_mapping)


def parse_opencv_yaml(text: str, path: str | Path | None = None) -> dict[str, Any]:
    """Parse the text of an OpenCV / EuRoC YAML file into a dict."""
    lines = text.splitlines()
    body: list[str] = []
    seen_content = False
    for line in lines:
        if not seen_content and _DIRECTIVE.match(line):
            body.append("")  # keep line numbers in PyYAML's messages
            continue
        if not seen_content and line.strip() == "---":
            body.append("")
            continue
        if line.strip() and not line.lstrip().startswith("#"):
            seen_content = True
        body.append(line)
    try:
        data = yaml.load("\n".join(body), Loader=_OpenCvLoader)  # noqa: S506 (safe subclass)
    except yaml.YAMLError as err:
        raise DataError(f"malformed YAML: {err}", path) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DataError(f"expected a mapping at the top level, got {type(data).__name__}", path)
    return data


def read_opencv_yaml(path: str | Path) -> dict[str, Any]:
    """Read an OpenCV / EuRoC ``sensor.yaml`` (``%YAML:1.0`` header allowed) into a dict."""
    path = Path(path)
    if not path.is_file():
        raise DataError("missing YAML file", path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read YAML file: {err}", path) from None
    return parse_opencv_yaml(text, path)


def matrix_from_yaml(value: Any, shape: tuple[int, int] | None = None, *,
                     path: str | Path | None = None, key: str = "matrix") -> np.ndarray:
    """A float64 matrix from ``{rows, cols, data}`` (EuRoC/OpenCV) or a (nested) list.

    ``shape`` (rows, cols), when given, is enforced.
    """
    try:
        if isinstance(value, dict):
            if "data" not in value:
                raise ValueError("no 'data' entry")
            data = np.asarray(value["data"], dtype=np.float64).ravel()
            rows = int(value.get("rows", shape[0] if shape else 0))
            cols = int(value.get("cols", shape[1] if shape else 0))
            if rows * cols != data.size:
                raise ValueError(f"rows*cols = {rows}*{cols} but {data.size} values")
            mat = data.reshape(rows, cols)
        else:
            mat = np.asarray(value, dtype=np.float64)
            if shape is not None and mat.ndim == 1 and mat.size == shape[0] * shape[1]:
                mat = mat.reshape(shape)
    except (TypeError, ValueError) as err:
        raise DataError(f"{key}: not a matrix ({err})", path) from None
    if shape is not None and mat.shape != tuple(shape):
        raise DataError(f"{key}: expected shape {tuple(shape)}, got {mat.shape}", path)
    if not np.all(np.isfinite(mat)):
        raise DataError(f"{key}: non-finite values", path)
    return mat


def imu_noise_from_yaml(entries: Mapping[str, float]) -> ImuNoise:
    """:class:`ImuNoise` from the four noise entries of an IMU ``sensor.yaml`` (any mapping
    holding the keys of :data:`IMU_NOISE_KEYS`; the readers validate the numbers first)."""
    return ImuNoise(**{name: float(entries[key]) for key, name in IMU_NOISE_KEYS.items()})


def imu_noise_to_yaml(noise: ImuNoise) -> dict[str, float]:
    """The four ``sensor.yaml`` noise entries of ``noise`` (scalar densities), keyed and
    ordered as EuRoC writes them."""
    return {key: float(getattr(noise, name)) for key, name in IMU_NOISE_KEYS.items()}
