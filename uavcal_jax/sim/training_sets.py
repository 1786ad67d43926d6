"""Simulated training sets (the calibrator's), rendered once into a cache and reused by every
sweep.

Three families (:data:`FAMILIES`):

- ``"euroc"``: one sequence per EuRoC ground-truth trajectory in
  ``<data_root>/trajectories/euroc/`` (11, real indoor MAV dynamics), over its whole length;
- ``"uzh_fpv"``: the same for the 11 UZH-FPV trajectories (aggressive racing-drone flight);
- ``"procedural"``: seeded procedural flights of the simulator (no data needed).

Each sequence is a :func:`uavcal_jax.sim.cache.cached_simulation` (a folder per
configuration, written atomically). Frames are rendered at
:data:`~uavcal_jax.sim.config.LOW_RESOLUTION` (half EuRoC's, the EuRoC lens scaled) and
reach the model through the same resize as real frames (``WindowConfig.size``,
``INTER_AREA``); only cam0 is read. The IMU is EuRoC's ADIS16448 model with its turn-on
biases, so the "clean" training IMU is as clean as a real one: the injected offset comes on
top of an unknown bias, as in the paper.

``data_root`` (the folder holding ``trajectories/``) is the callers': the experiments pass the
repository's ``../shared/data``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim.cache import cached_simulation, trajectory_span
from uavcal_jax.sim.config import LOW_RESOLUTION, SimConfig

__all__ = ["FAMILIES", "SimSetConfig", "sequence_configs",
           "simulated_set", "trajectory_dir"]

FAMILIES = ("euroc", "uzh_fpv", "procedural")


def trajectory_dir(data_root: str | Path, family: str) -> Path:
    """Folder of a family's TUM trajectories, ``data_root/trajectories/<family>``."""
    return Path(data_root) / "trajectories" / family


@dataclass(frozen=True)
class SimSetConfig:
    """One simulated set.

    Attributes:
        family: one of :data:`FAMILIES`.
        max_duration: seconds per sequence at most (``None``: each trajectory's whole
            length; procedural flights need a value, default 30 s).
        sequences: names to keep (trajectory file stems, or ``"proc_00"``...); ``None``: all.
        count: procedural flights (``proc_00`` ... ``proc_{count-1}``).
        resolution: render size.
        color: ``"gray"`` or ``"rgb"`` (the RGB path).
        seed: base seed (sequence ``i`` uses ``seed + i``).
        airframes: procedural flights' airframes: ``"ideal"`` (the thrust exactly along
            ``a + g e_z``, the IMU square on the body: the accelerometer's x and y read the
            offset alone) or ``"realistic"`` (each flight draws, from its seed, the airframe
            a real multirotor is: :data:`REALISTIC_AIRFRAME`'s rotor drag, thrust-axis tilt
            and IMU mounting tilt).
    """

    family: str = "euroc"
    max_duration: float | None = None
    sequences: tuple[str, ...] | None = None
    count: int = 8
    resolution: tuple[int, int] = LOW_RESOLUTION
    color: str = "gray"
    seed: int = 0
    airframes: str = "ideal"

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"family must be one of {FAMILIES}, got {self.family!r}")
        if self.airframes not in AIRFRAMES:
            raise ValueError(f"airframes must be one of {AIRFRAMES}, got {self.airframes!r}")


#: :attr:`SimSetConfig.airframes`.
AIRFRAMES = ("ideal", "realistic")
#: The ranges a realistic airframe is drawn from: rotor drag uniform in this range, 1/s
#: (0.3-0.6 measured on small quadrotors, Faessler et al. 2018 and Svacha et al. 2017), and
#: the thrust axis's tilt in the body and the IMU's mounting tilt on the airframe each
#: normal per axis with this standard deviation, degrees (a frame's asymmetry and a board's
#: mounting: a degree or so).
REALISTIC_AIRFRAME = {"rotor_drag": (0.2, 0.6), "thrust_tilt_std_deg": 1.0,
                      "imu_tilt_std_deg": 1.0}


def realistic_airframe(seed: int) -> dict[str, Any]:
    """:class:`~uavcal_jax.sim.config.SimConfig` fields of an airframe drawn from ``seed``
    (:data:`REALISTIC_AIRFRAME`)."""
    rng = np.random.default_rng([seed, 0xA1F])
    r = REALISTIC_AIRFRAME
    thrust = rng.normal(0.0, r["thrust_tilt_std_deg"], 2)
    imu = rng.normal(0.0, r["imu_tilt_std_deg"], 3)
    return {"rotor_drag": round(float(rng.uniform(*r["rotor_drag"])), 4),
            "thrust_tilt_deg": tuple(round(float(v), 4) for v in thrust),
            "imu_rotation_deg": tuple(round(float(v), 4) for v in imu)}


def sequence_configs(config: SimSetConfig, data_root: str | Path | None = None
                     ) -> list[tuple[str, SimConfig]]:
    """``(name, SimConfig)`` of every sequence of the set; ``data_root`` holds the
    trajectory families' files (:func:`trajectory_dir`; procedural flights need none).

    Raises:
        ValueError: a trajectory family without ``data_root``, or unknown ``sequences``.
        FileNotFoundError: no trajectory files under ``data_root``.
    """
    base = dict(resolution=config.resolution, color=config.color, depth=False, targets=False)
    out: list[tuple[str, SimConfig]] = []
    if config.family == "procedural":
        duration = 30.0 if config.max_duration is None else config.max_duration
        for i in range(config.count):
            airframe = (realistic_airframe(config.seed + i)
                        if config.airframes == "realistic" else {})
            out.append((f"proc_{i:02d}", SimConfig(duration=duration, seed=config.seed + i,
                                                   **base, **airframe)))
    else:
        if data_root is None:
            raise ValueError(f"the {config.family} set needs data_root (the folder holding "
                             "trajectories/)")
        folder = trajectory_dir(data_root, config.family)
        files = sorted(folder.glob("*.txt"))
        if not files:
            raise FileNotFoundError(f"no trajectories in {folder}")
        for i, path in enumerate(files):
            # the last 0.1 s stays inside the file, whatever its rate
            span = round(trajectory_span(path) - 0.1, 1)
            duration = span if config.max_duration is None else min(span, config.max_duration)
            out.append((path.stem, SimConfig(trajectory=str(path), duration=duration,
                                             seed=config.seed + i, **base)))
    if config.sequences is not None:
        wanted = set(config.sequences)
        unknown = wanted - {n for n, _ in out}
        if unknown:
            raise ValueError(f"unknown {config.family} sequences: {sorted(unknown)}")
        out = [(n, c) for n, c in out if n in wanted]
    return out


def simulated_set(config: SimSetConfig, cache: str | Path, *,
                  data_root: str | Path | None = None, progress: bool = True) -> list[Path]:
    """The set's sequence folders under ``cache/<family>/``, rendering the missing ones
    (``data_root``: :func:`sequence_configs`)."""
    items: Sequence[tuple[str, SimConfig]] = sequence_configs(config, data_root)
    root = Path(cache) / config.family
    return [cached_simulation(cfg, root, name, progress=progress)
            for name, cfg in progress_bar(items, desc=f"{config.family} set",
                                          enabled=progress, unit="seq")]
