"""How far a corrected IMU carries a drone: IMU-only dead reckoning and the stereo VIO over one
recording, under each offset estimator's correction (the calibrator paper's section 5
evaluation; ``experiments/drift_long_flight.py`` is its command).

For a recording (:func:`evaluate_recording`):

1. the **corrections** (:func:`corrections`): ``raw`` (nothing subtracted); each named
   estimator's offset, estimated blind by
   :func:`~uavcal_jax.pipeline.predict_offset.predict_offset` (it hides the ground truth from
   the estimator); ``true``, the true total constant error (the injected offset plus the
   simulated sensor's own turn-on bias, averaged over the flight;
   :func:`uavcal_jax.data.true_offset.true_offset` with label ``total``);
2. per correction (:func:`evaluate_correction`): dead reckoning of the corrected IMU from the
   true state at its first sample (:func:`uavcal_jax.imu.dead_reckoning.dead_reckon`) and the
   VIO on the corrected IMU (:func:`uavcal_jax.vio.run.run_vio`), each scored by its final
   position error and error curve against distance travelled
   (:func:`~uavcal_jax.pipeline.drift_metrics.drift_curve`: dead reckoning as it is, the VIO
   aligned over its first metres) and its ATE (SE(3)-aligned RMSE,
   :func:`~uavcal_jax.vio.trajectory_metrics.trajectory_errors`).

Flights (:class:`DriftFlight`, :func:`simulate_flight`): a straight line
(:func:`~uavcal_jax.sim.flights.straight_flight`) or a procedural loop with outdoor-sized
limits (:data:`LOOP_LIMITS`), written as a TUM file and simulated through the cache
(:func:`~uavcal_jax.sim.cache.cached_simulation`) with a constant IMU offset.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import jax
import numpy as np

from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sequence import GroundTruth, Sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.data.true_offset import true_offset
from uavcal_jax.errors import DataError
from uavcal_jax.geometry import so3
from uavcal_jax.imu.dead_reckoning import dead_reckon
from uavcal_jax.pipeline.drift_metrics import DEFAULT_ALIGN_M, drift_curve
from uavcal_jax.pipeline.predict_offset import predict_offset, score
from uavcal_jax.sim.cache import cached_simulation, trajectory_span
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.flight_file import write_flight
from uavcal_jax.sim.flights import FlightConfig, procedural_flight, straight_flight
from uavcal_jax.sim.trajectory import Trajectory
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.run import run_vio
from uavcal_jax.vio.trajectory_metrics import trajectory_errors

__all__ = ["FLIGHT_KINDS", "LOOP_LIMITS", "OFFSET_RANGE", "RAW", "TRUE", "DriftFlight",
           "corrections", "dead_reckoning", "evaluate_correction", "evaluate_recording",
           "flight_trajectory", "physical_offset", "simulate_flight"]

#: The correction that subtracts nothing, and the one that subtracts the true total error.
RAW, TRUE = "raw", "true"
#: :attr:`DriftFlight.kind` values.
FLIGHT_KINDS = ("straight", "loop")
#: A procedural loop's limits: an outdoor drone's speeds over a 60 m square, long legs.
LOOP_LIMITS = FlightConfig(max_speed=5.0, max_accel=2.0, max_vertical_speed=1.0,
                           area_half_size=(30.0, 30.0), altitude_range=(1.0, 4.0),
                           leg_length=(10.0, 40.0))
#: The physical range of a miscalibration (per axis magnitude): gyro rad/s, accel m/s^2.
OFFSET_RANGE = ((0.01, 0.03), (0.05, 0.15))
# dead-reckoned states kept for the curves and the ATE: every k-th IMU sample (10 Hz at 200 Hz)
_DR_STRIDE = 20


@dataclasses.dataclass(frozen=True)
class DriftFlight:
    """One simulated flight of the drift study.

    Attributes:
        name: its label (and the cache folder's prefix).
        kind: ``"straight"`` (``length_m`` at ``speed``) or ``"loop"`` (a procedural flight of
            ``duration_s`` under :data:`LOOP_LIMITS`, seeded by ``seed``).
        length_m, speed: the straight line, metres and m/s.
        duration_s: the loop's duration, seconds.
        seed: the loop's plan and the simulation's noise, scene and camera seed.
    """

    name: str
    kind: str = FLIGHT_KINDS[0]
    length_m: float = 1000.0
    speed: float = 10.0
    duration_s: float = 120.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in FLIGHT_KINDS:
            raise ValueError(f"kind must be one of {FLIGHT_KINDS}, got {self.kind!r}")


def physical_offset(seed: int) -> np.ndarray:
    """A constant IMU offset (6,) in :data:`OFFSET_RANGE`: per-axis magnitudes drawn uniformly,
    random signs, from ``numpy.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    lo = np.repeat([r[0] for r in OFFSET_RANGE], 3)
    hi = np.repeat([r[1] for r in OFFSET_RANGE], 3)
    return rng.uniform(lo, hi) * rng.choice([-1.0, 1.0], 6)


def flight_trajectory(flight: DriftFlight) -> Trajectory:
    """The planned flight (quadrotor body frame: x forward, z up)."""
    if flight.kind == "straight":
        return straight_flight(flight.length_m, flight.speed)
    return procedural_flight(flight.seed, flight.duration_s, LOOP_LIMITS)


def simulate_flight(flight: DriftFlight, cache: str | Path, imu_offset, *,
                    resolution: tuple[int, int], progress: bool = True) -> Path:
    """The recording of ``flight`` with the constant ``imu_offset`` (6,) at ``resolution``,
    simulated under ``cache`` unless it is there already. Returns its folder."""
    cache = Path(cache)
    tum = write_flight(flight_trajectory(flight), cache / "flights" / f"{flight.name}.txt")
    # a margin at both ends: the simulator's fit of the file is least certain there
    span = trajectory_span(tum)
    config = SimConfig(trajectory=str(tum), start=0.25, duration=math.floor(span - 0.5),
                       body_frame="flu", resolution=tuple(resolution), seed=flight.seed,
                       imu_offset=tuple(float(v) for v in imu_offset), targets=False,
                       depth=False)
    return cached_simulation(config, cache, flight.name, progress=progress)


def corrections(recording: str | Path, methods, *, progress: bool = False) -> dict[str, dict]:
    """The offsets to subtract, by correction name: :data:`RAW`, each of ``methods`` (blind,
    :func:`~uavcal_jax.pipeline.predict_offset.predict_offset`) and :data:`TRUE`.

    Returns:
        per name: ``offset`` (6,) the value subtracted, ``seconds`` to estimate it and, for
        the methods, ``summary`` (``predict_offset``'s, JSON-ready, with ``score``'s figures).

    Raises:
        DataError: the recording has no ground truth with bias columns (no true offset).
    """
    sequence, _ = read_sequence(recording)
    recorded = recorded_imu_offset(recording)
    truth = true_offset("total", recorded, sequence.ground_truth)
    if truth is None:
        raise DataError("the drift study needs the ground truth's IMU bias columns",
                        recording)
    out: dict[str, dict] = {RAW: {"offset": np.zeros(6), "seconds": 0.0}}
    for method in methods:
        t = time.perf_counter()
        summary, estimate = predict_offset(sequence, method, progress=progress)
        summary.update(score(estimate, recorded, sequence.ground_truth))
        out[method] = {"offset": np.asarray(estimate.offset, np.float64),
                       "seconds": time.perf_counter() - t, "summary": summary}
    out[TRUE] = {"offset": truth, "seconds": 0.0}
    return out


def dead_reckoning(sequence: Sequence, offset) -> GroundTruth:
    """The IMU of ``sequence`` minus ``offset`` (6,), dead-reckoned from the true state at the
    first IMU sample that the ground truth has a state at (within 1 ms); every
    ``_DR_STRIDE``-th state, as a trajectory.

    Raises:
        DataError: no ground truth with velocities, or none at an IMU sample.
    """
    gt, imu = sequence.ground_truth, sequence.imu
    if gt is None or gt.velocity is None or imu is None:
        raise DataError("dead reckoning needs an IMU and a ground truth with velocities",
                        sequence.root or sequence.name)
    k = int(np.searchsorted(imu.t_ns, gt.t_ns[0]))
    if k >= len(imu) or abs(int(imu.t_ns[k]) - int(gt.t_ns[0])) > 1_000_000:
        raise DataError("no IMU sample within 1 ms of the ground truth's first state",
                        sequence.root or sequence.name)
    with jax.enable_x64(True):
        R, _, p = dead_reckon(np.diff(imu.t_ns[k:]) * 1e-9, imu.gyro[k:], imu.accel[k:],
                              so3.from_quaternion(np.asarray(gt.quaternion[0], np.float64)),
                              gt.velocity[0], gt.position[0], np.asarray(offset, np.float64))
        keep = slice(None, None, _DR_STRIDE)
        q = np.asarray(so3.to_quaternion(R[keep]))
        p = np.asarray(p[keep])
    return GroundTruth(np.asarray(imu.t_ns[k:][keep], np.int64), p, q)


def _scores(estimate: GroundTruth, gt: GroundTruth, align_m: float | None) -> dict:
    """Final error, ATE and the drift curve of one trajectory (JSON-ready but the curve)."""
    curve = drift_curve(estimate, gt, align_m=align_m)
    distance = float(curve["distance_m"][-1])
    final = float(curve["error_m"][-1])
    return {"final_error_m": final, "distance_m": distance,
            "final_error_pct": 100.0 * final / distance if distance > 0 else None,
            "ate_m": trajectory_errors(estimate, gt)["ate_m"]["rmse"],
            "poses": len(estimate), "curve": curve}


def evaluate_correction(sequence: Sequence, offset, *, vio_config: VioConfig | None = None,
                        align_m: float = DEFAULT_ALIGN_M, progress: bool = False) -> dict:
    """Dead reckoning and the VIO of ``sequence``'s IMU minus ``offset`` (6,).

    Returns:
        ``dead_reckoning`` and ``vio``, each ``final_error_m``, ``distance_m``,
        ``final_error_pct``, ``ate_m``, ``poses`` and ``curve`` (:func:`drift_curve`'s
        arrays); the VIO's also ``resets`` and ``seconds``.
    """
    gt = sequence.ground_truth
    out = {"dead_reckoning": _scores(dead_reckoning(sequence, offset), gt, None)}
    t = time.perf_counter()
    result = run_vio(sequence, vio_config, offset, show_progress=progress)
    seconds = time.perf_counter() - t
    traj = result.trajectory()
    finite = np.all(np.isfinite(traj.position), axis=1)
    if finite.sum() < 3:
        out["vio"] = {"final_error_m": None, "ate_m": None, "poses": int(finite.sum()),
                      "resets": result.resets, "seconds": seconds, "curve": None}
        return out
    traj = GroundTruth(traj.t_ns[finite], traj.position[finite], traj.quaternion[finite])
    out["vio"] = {**_scores(traj, gt, align_m), "resets": result.resets, "seconds": seconds}
    return out


def evaluate_recording(recording: str | Path, methods, *, vio_config: VioConfig | None = None,
                       align_m: float = DEFAULT_ALIGN_M, progress: bool = False) -> dict:
    """:func:`corrections` and :func:`evaluate_correction` for each of them.

    Returns:
        ``true_offset`` (6,) and per correction name: ``offset`` (6,), ``offset_error`` (6,)
        (the offset minus the truth: what stays in the corrected IMU), ``gyro_rms`` (rad/s)
        and ``accel_rms`` (m/s^2) of it, ``estimate_seconds``, the estimator's ``summary``
        (methods only) and :func:`evaluate_correction`'s ``dead_reckoning`` and ``vio``.
    """
    fixes = corrections(recording, methods, progress=progress)
    sequence, _ = read_sequence(recording)
    truth = fixes[TRUE]["offset"]
    rows = {}
    for name, fix in fixes.items():
        err = fix["offset"] - truth
        rows[name] = {"offset": fix["offset"], "offset_error": err,
                      "gyro_rms": float(np.sqrt(np.mean(err[:3] ** 2))),
                      "accel_rms": float(np.sqrt(np.mean(err[3:] ** 2))),
                      "estimate_seconds": fix["seconds"],
                      **({"summary": fix["summary"]} if "summary" in fix else {}),
                      **evaluate_correction(sequence, fix["offset"], vio_config=vio_config,
                                            align_m=align_m, progress=progress)}
    return {"true_offset": truth, "corrections": rows}
