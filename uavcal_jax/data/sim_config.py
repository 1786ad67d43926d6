"""``sim_config.json``: the record a simulated recording carries beside its ``mav0`` folder.

``uavcal simulate`` (:mod:`uavcal_jax.sim.simulate`) writes it last, so its presence marks a
folder as a complete simulation (one that ``--overwrite`` may replace, that the simulation
cache may reuse). One JSON object:

- ``uavcal_jax_version``: the writer's version;
- ``config``: every field of the simulator's configuration
  (:meth:`uavcal_jax.sim.config.SimConfig.to_dict`), among them ``imu_offset``: the constant
  offset added to the written IMU, 6 numbers (gyro rad/s xyz, accel m/s^2 xyz), or ``null``;
  ``body_frame`` (``euroc`` or ``flu``: the trajectory file's body convention),
  ``camera_pitch_deg`` (the stereo rig's pitch below the body's forward axis, ``null``: EuRoC's
  rig as it is) and ``follow_targets`` (targets planned into the camera's view: track ids
  ``0 .. N-1``, their world paths in ``target0/track.csv``);
- ``seeds``: the seed of each stage;
- ``flight``: where the trajectory came from, and ``t_start_ns`` / ``t_end_ns`` (the IMU's
  first and last timestamps); for a trajectory file also ``body_frame`` and ``trajectory_fit``
  (:class:`uavcal_jax.sim.trajectory_fit.FitReport`), an object of numbers: ``poses``,
  ``merged`` (near-duplicate stamps merged), ``jumps`` (position steps removed),
  ``median_period_s``, ``max_gap_s``, ``knot_spacing_s``, ``smoothing_position``,
  ``smoothing_rotation`` (the penalty weights chosen), ``position_noise_m`` /
  ``rotation_noise_rad`` (the noise measured on the poses) and ``position_residual_rms_m`` /
  ``rotation_residual_rms_rad`` (RMS fit residual; both as 3-D magnitudes: metres, and the
  angle between fitted and recorded orientation in radians), and over the simulated window
  ``peak_specific_force_mps2`` (max ``|a - g|``, what an accelerometer reads),
  ``peak_acceleration_mps2`` (max kinematic ``|a|``) and ``peak_angular_rate_radps``;
- ``imu_noise``: the noise densities, bias random walks and turn-on bias (``null`` without
  noise); ``imu_calibration``: the IMU calibration written;
- ``counts``: samples and frames written per stream;
- with frames: ``cameras`` (each camera's calibration), ``camera_model``, ``scene``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from uavcal_jax.errors import DataError

__all__ = ["SIM_CONFIG_FILE", "read_sim_config", "recorded_imu_offset", "write_sim_config"]

#: The record's file name, in the recording's folder.
SIM_CONFIG_FILE = "sim_config.json"


def write_sim_config(folder: str | Path, record: Mapping[str, Any]) -> Path:
    """Write ``record`` (the layout of the module docstring) as ``folder/sim_config.json``,
    indented JSON; returns its path."""
    path = Path(folder) / SIM_CONFIG_FILE
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def read_sim_config(folder: str | Path) -> dict | None:
    """The record of a simulated recording ``folder``; ``None`` when it has none (not a
    simulation).

    Raises:
        DataError: a ``sim_config.json`` that is not a readable JSON object.
    """
    path = Path(folder) / SIM_CONFIG_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DataError(f"not a readable simulator record ({err})", path) from None
    if not isinstance(record, dict):
        raise DataError("not a readable simulator record (not a JSON object)", path)
    return record


def recorded_imu_offset(folder: str | Path) -> np.ndarray | None:
    """The ``(6,)`` IMU offset a simulated recording carries (``config.imu_offset``: gyro
    rad/s xyz, accel m/s^2 xyz); ``None`` when ``folder`` has no ``sim_config.json`` or it
    records no offset.

    Raises:
        DataError: an unreadable record, or one without ``config``.
    """
    record = read_sim_config(folder)
    if record is None:
        return None
    config = record.get("config")
    if not isinstance(config, dict):
        raise DataError("not a readable simulator record (no config.imu_offset)",
                        Path(folder) / SIM_CONFIG_FILE)
    value = config.get("imu_offset")
    return None if value is None else np.asarray(value, np.float64)
