"""A planned flight (:class:`~uavcal_jax.sim.trajectory.Trajectory`) written as a TUM file, so
the simulator (``SimConfig.trajectory``) flies flights other than its built-in procedural one:
a :func:`~uavcal_jax.sim.flights.straight_flight`, or a procedural flight with other limits.

The flight's body frame is the planner's quadrotor frame (x forward, y left, z up): simulate
the file with ``SimConfig(body_frame="flu")``, which mounts EuRoC's IMU and rig on it as on the
built-in procedural flights.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.data.euroc_rig import EUROC_IMU_RATE_HZ
from uavcal_jax.data.tum import write_tum
from uavcal_jax.sim.imu_synth import ground_truth_from_trajectory, imu_timestamps
from uavcal_jax.sim.trajectory import Trajectory

__all__ = ["write_flight"]


def write_flight(trajectory: Trajectory, path: str | Path,
                 rate_hz: float = EUROC_IMU_RATE_HZ) -> Path:
    """Write ``trajectory``'s poses at ``rate_hz`` over its whole span as a TUM file
    (seconds, world metres, body-to-world quaternion). Returns ``path``."""
    t_ns = imu_timestamps(trajectory.t_start, trajectory.t_end, rate_hz)
    return write_tum(path, ground_truth_from_trajectory(trajectory, t_ns))
