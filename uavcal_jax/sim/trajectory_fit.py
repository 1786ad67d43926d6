"""Fit a smooth :class:`~uavcal_jax.sim.trajectory.Trajectory` to recorded ground truth.

:func:`fit_tum_trajectory` fits a recorded ground truth (a TUM file or a
:class:`~uavcal_jax.data.sequence.GroundTruth`) with penalised least-squares quintic
B-splines (knots every :attr:`FitConfig.knot_spacing` seconds, a third-difference penalty);
:func:`fit_trajectory_report` does the same and says how the fit went (:class:`FitReport`).
The file's own clock is kept: ``t_start`` / ``t_end`` are absolute seconds of that clock.

Recordings come as they come, so the poses are prepared first:

1. Near-duplicate stamps (closer than :attr:`FitConfig.merge_fraction` of the typical sample
   period; motion-capture exports have pairs 0.03 ms apart) are merged into one pose (mean
   time, position and quaternion): two noisy positions 30 us apart are a velocity of tens of
   m/s to anything that differentiates them. A member that differs from the others by more
   than the noise and the motion allow (timestamp jitter: a pose stamped a sample period or
   more from when it was taken, centimetres off at flight speed) is dropped instead, with a
   :class:`~uavcal_jax.errors.DataRepairWarning` naming the file and the count
   (:func:`~uavcal_jax.sim.pose_samples.drop_inconsistent_duplicates`). Averaged in, each
   would be an outlier; read as position steps, they once shifted the flight by decimetres.
2. Instantaneous position steps (EuRoC's Machine Hall ground truth has dozens) are replaced
   by smooth ramps of the same size (:func:`remove_position_jumps`, which allows for
   irregular sample intervals): the fit keeps to the file's poses away from each step.
3. Each pose is weighted by the time it stands for (half the span to its neighbours, at most
   one typical period), so a dense burst of samples counts as much as the same time sampled
   regularly and no more.
4. The noise of the positions and of the orientations is measured on the data
   (:func:`sample_noise`, :func:`rotation_noise`: a robust spread of each sample's deviation
   from the cubic through its four neighbours, which removes any motion smoother than a
   cubic over those samples).
5. The smoothing is chosen per block (position; rotation) so that the weighted RMS residual
   of the fit equals that noise (Morozov's discrepancy principle), never below
   :attr:`FitConfig.smoothing`. On EuRoC's 200 Hz ground truth (smooth at the sample scale:
   a few micrometres of sample noise, while the least-squares fit leaves ~0.05 mm of motion
   above its band) the floor already leaves more residual than that, and the fit is the
   plain least-squares fit it always was (flat to ~5 Hz, rolled off above ~8 Hz); on noisy
   data (1 mm at 50 Hz) the penalty rises until the fit stops following the noise. In a gap
   (no samples for up to a second or so) the penalty alone sets the coefficients: the bridge
   is the smoothest quintic that joins the two sides, without oscillation.

Flight limits. :class:`FitReport` records the fit's residual and the peak specific force and
angular rate of the fitted motion; :func:`check_flight_limits` warns
(:class:`~uavcal_jax.errors.FlightLimitWarning`) when they exceed what a drone flies and refuses
(:class:`~uavcal_jax.errors.DataError`) when only a broken file can explain them (the
thresholds are :class:`FitConfig` fields).

The preparation steps are :mod:`uavcal_jax.sim.pose_samples`.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy.interpolate import BSpline

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError, DataRepairWarning, FlightLimitWarning
from uavcal_jax.geometry.frames import GRAVITY, GRAVITY_W
from uavcal_jax.sim.pose_samples import (
    RAMP_ACCELERATION,
    drop_inconsistent_duplicates,
    merge_near_duplicates,
    remove_position_jumps,
    rotation_noise,
    sample_noise,
    time_weights,
    typical_period,
)
from uavcal_jax.sim.trajectory import DEGREE, Trajectory, sign_continuous, uniform_knots

__all__ = [
    "FitConfig",
    "FitReport",
    "check_flight_limits",
    "fit_trajectory_report",
    "fit_tum_trajectory",
    "motion_peaks",
    "remove_position_jumps",
]

#: Normal-consistent scale of the median absolute deviation.
_MAD_SCALE = 1.4826


@dataclass(frozen=True)
class FitConfig:
    """How :func:`fit_tum_trajectory` smooths recorded poses, and what a drone can fly.

    Attributes:
        knot_spacing: seconds between B-spline knots (0.05 s: flat response to ~5 Hz, cut-off
            near 10 Hz). It is widened to ``min_samples_per_knot`` sample periods for sparse
            data (e.g. 20 Hz ground truth gets 0.1 s).
        smoothing: the smallest weight of the third-difference penalty on the spline
            coefficients, relative to the data term per knot interval. 1e-4 barely changes the
            least-squares fit (gain 0.9 at 8 Hz); it keeps the solve well posed across gaps.
        match_noise: raise the penalty until the fit's residual equals the noise measured on
            the data (see the module docstring); ``False``: always ``smoothing``.
        edge_padding: seconds of extra data fitted on each side of a requested
            ``start``/``duration`` window (when the source has them), so the window's ends
            are free of spline edge effects.
        min_samples_per_knot: see ``knot_spacing``.
        merge_fraction: stamps closer than this fraction of the typical sample period are
            merged into one pose, or dropped where they disagree (see
            :func:`~uavcal_jax.sim.pose_samples.drop_inconsistent_duplicates`, which takes
            ``jump_threshold`` as its floor); 0 disables it.
        jump_threshold: metres; position steps larger than this (and than
            ``jump_sigmas`` robust standard deviations of the data's noise) that the
            neighbouring samples do not share are replaced by ramps before fitting, see
            :func:`remove_position_jumps`. ``None`` disables it.
        jump_sigmas, jump_max_jerk: see :func:`remove_position_jumps`.
        jump_ramp_acceleration: m/s^2; the peak acceleration of the ramp that replaces a
            position step (:func:`~uavcal_jax.sim.pose_samples.step_ramps`): a 5 cm step
            becomes a 3.8 s ramp, a 1 mm step a 0.5 s one.
        warn_specific_force: m/s^2; a peak specific force (what an accelerometer reads,
            ``|a - g|``: thrust over mass for a multirotor) above this gets a
            :class:`~uavcal_jax.errors.FlightLimitWarning`. 4 g: an agile quadrotor's
            thrust-to-weight ratio,
            above every EuRoC and UZH-FPV racing flight (their fits peak at 1.1-2.9 g).
        warn_angular_rate: rad/s; likewise for the peak body rate (20 rad/s: ~1150 deg/s,
            a fast flip; those flights peak under 7 rad/s).
        refuse_specific_force: m/s^2; above this (50 g) no airframe flew it: the file is
            broken (position steps, mixed-up units or timestamps) and
            :func:`check_flight_limits` raises ``DataError``.
        refuse_angular_rate: rad/s; likewise (100 rad/s: 16 turns a second).
    """

    knot_spacing: float = 0.05
    smoothing: float = 1e-4
    match_noise: bool = True
    edge_padding: float = 1.0
    min_samples_per_knot: float = 2.0
    merge_fraction: float = 0.1
    jump_threshold: float | None = 5e-4
    jump_sigmas: float = 8.0
    jump_max_jerk: float = 100.0
    jump_ramp_acceleration: float = RAMP_ACCELERATION
    warn_specific_force: float = 4.0 * GRAVITY
    warn_angular_rate: float = 20.0
    refuse_specific_force: float = 50.0 * GRAVITY
    refuse_angular_rate: float = 100.0


@dataclass(frozen=True)
class FitReport:
    """How a fit went (``sim_config.json``'s ``flight.trajectory_fit``).

    Residuals and noise are 3-D magnitudes over the poses inside the trajectory's span
    (``[t_start, t_end]``, padding excluded) as fitted (near-duplicates merged or dropped,
    position steps ramped): position in metres, rotation as the angle between fitted and recorded
    orientation in radians. The noise figures are the data's own
    (:func:`sample_noise`), expressed the same way (RMS magnitude of the noise vector), so a
    residual close to its noise means the fit removed the noise and little motion.

    Attributes:
        poses: poses read inside the fitted interval (span plus padding).
        merged: poses merged away as near-duplicate stamps.
        dropped: near-duplicate poses dropped as inconsistent with their twins (timestamp
            jitter).
        jumps: position steps replaced by ramps.
        median_period_s: typical sample interval (near-duplicates aside).
        max_gap_s: longest interval between fitted poses.
        knot_spacing_s: the spline's knot spacing.
        smoothing_position, smoothing_rotation: the penalty weights chosen.
        position_noise_m, rotation_noise_rad: measured noise.
        position_residual_rms_m, rotation_residual_rms_rad: RMS fit residual.
        peak_specific_force_mps2: max ``|a_W - g_W|`` over the span (what an accelerometer
            reads; 9.81 hovering).
        peak_acceleration_mps2: max kinematic ``|a_W|`` (gravity not included).
        peak_angular_rate_radps: max body rate magnitude.
    """

    poses: int
    merged: int
    dropped: int
    jumps: int
    median_period_s: float
    max_gap_s: float
    knot_spacing_s: float
    smoothing_position: float
    smoothing_rotation: float
    position_noise_m: float
    rotation_noise_rad: float
    position_residual_rms_m: float
    rotation_residual_rms_rad: float
    peak_specific_force_mps2: float
    peak_acceleration_mps2: float
    peak_angular_rate_radps: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready values."""
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------------------------
# Preparing the samples
# --------------------------------------------------------------------------------------------


class _PenalisedFit:
    """Weighted, penalised least-squares quintic spline coefficients for a fixed design:
    minimise ``sum_i w_i |B_i c - y_i|^2 / per_knot + smoothing * |D3 c|^2`` with
    ``per_knot = sum(w) / (number of coefficients)`` (so ``smoothing`` is relative to the
    data term of one knot interval)."""

    def __init__(self, tau: np.ndarray, weights: np.ndarray, knots: np.ndarray, order: int = 3):
        self.B = BSpline.design_matrix(tau, knots, DEGREE).tocsr()
        m = self.B.shape[1]
        D = sparse.eye(m, format="csr")
        for _ in range(order):
            D = D[1:] - D[:-1]
        self.weights = weights
        self.per_knot = float(np.sum(weights)) / m
        W = sparse.diags(weights / self.per_knot)
        self.gram = (self.B.T @ W @ self.B).tocsc()
        self.penalty = (D.T @ D).tocsc()
        self.WB = (W @ self.B).T.tocsr()

    def coefficients(self, values: np.ndarray, smoothing: float) -> np.ndarray:
        lu = sparse_linalg.splu(sparse.csc_matrix(self.gram + smoothing * self.penalty))
        return lu.solve(np.asarray(self.WB @ values))

    def residual_ms(self, values: np.ndarray, smoothing: float) -> tuple[float, np.ndarray]:
        """Weighted mean over samples of the squared residual, summed over columns."""
        coef = self.coefficients(values, smoothing)
        r = self.B @ coef - values
        return float(np.sum(self.weights[:, None] * r**2) / np.sum(self.weights)), coef


def _noise_matched(fit: _PenalisedFit, values: np.ndarray, noise_var: float,
                   floor: float, iterations: int = 24) -> tuple[float, np.ndarray]:
    """Smallest smoothing >= ``floor`` whose weighted mean squared residual reaches
    ``noise_var`` (bisection on log smoothing; the residual grows with the smoothing).
    Returns ``(smoothing, coefficients)``."""
    ms, coef = fit.residual_ms(values, floor)
    if ms >= noise_var or noise_var <= 0.0:
        return floor, coef
    lo, hi = math.log(floor), math.log(1e12)
    ms_hi, coef_hi = fit.residual_ms(values, math.exp(hi))
    if ms_hi <= noise_var:
        return math.exp(hi), coef_hi
    for _ in range(iterations):
        m = 0.5 * (lo + hi)
        ms, coef_m = fit.residual_ms(values, math.exp(m))
        if ms < noise_var:
            lo = m
        else:
            hi, coef_hi = m, coef_m
    return math.exp(hi), coef_hi


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------


def _load_ground_truth(source) -> tuple[GroundTruth, str]:
    if isinstance(source, GroundTruth):
        return source, "ground-truth"
    path = Path(source)
    return read_tum(path), path.stem


def motion_peaks(traj: Trajectory, t: np.ndarray | None = None) -> dict[str, float]:
    """Peak specific force ``|a_W - g_W|`` (m/s^2, what an accelerometer reads), kinematic
    acceleration ``|a_W|`` (m/s^2) and body rate (rad/s) of ``traj`` at times ``t`` (float
    seconds; default every 5 ms over its span, ends included)."""
    if t is None:
        t = np.linspace(traj.t_start, traj.t_end, max(2, int(traj.duration / 0.005) + 1))
    state = traj.state(np.asarray(t, dtype=np.float64))
    return {
        "peak_specific_force_mps2": float(np.linalg.norm(
            state.acceleration - np.asarray(GRAVITY_W), axis=-1).max()),
        "peak_acceleration_mps2": float(np.linalg.norm(state.acceleration, axis=-1).max()),
        "peak_angular_rate_radps": float(np.linalg.norm(
            state.angular_velocity_body, axis=-1).max()),
    }


def _rotation_angle(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """(N,) angles in radians between the rotations of (N, 4) quaternions (either sign, any
    norm)."""
    dot = np.abs(np.sum(qa * qb, axis=-1)) / (np.linalg.norm(qa, axis=-1)
                                              * np.linalg.norm(qb, axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def fit_trajectory_report(source: str | Path | GroundTruth, start: float | None = None,
                          duration: float | None = None,
                          config: FitConfig = FitConfig(),  # noqa: B008
                          where: str | Path | None = None) -> tuple[Trajectory, FitReport]:
    """Fit a smooth trajectory to recorded poses (TUM file or ``GroundTruth``) and report on
    the fit.

    Position: one penalised least-squares quintic B-spline per axis (uniform knots). Rotation:
    the quaternions are made sign-continuous, each component is fitted the same way (with its
    own smoothing), and the result is normalised on evaluation (angular velocity from the
    unnormalised spline). The samples are prepared and the smoothing chosen as the module
    docstring describes.

    Args:
        source: a TUM file (``t tx ty tz qx qy qz qw``, read with
            :func:`uavcal_jax.data.tum.read_tum`) or a ``GroundTruth`` (its position and
            quaternion; other fields are ignored).
        start: first time of the trajectory, absolute seconds of the source's clock
            (default: the first pose). Clipped to the data.
        duration: seconds (default: to the last pose). Clipped to the data.
        config: smoothing settings.
        where: the file, for messages (default: ``source`` when it is a path).

    Returns:
        ``(trajectory, report)``: a :class:`Trajectory` with ``t_start``/``t_end`` in the
        source's own clock, and its :class:`FitReport`.

    Raises:
        DataError: too few poses, or a window that does not overlap the data.
    """
    gt, name = _load_ground_truth(source)
    if where is None and not isinstance(source, GroundTruth):
        where = Path(source)
    t_ns = np.asarray(gt.t_ns, dtype=np.int64)
    pos = np.asarray(gt.position, dtype=np.float64)
    quat = np.asarray(gt.quaternion, dtype=np.float64)
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"need at least {2 * (DEGREE + 1)} poses to fit a trajectory, "
                        f"got {len(t_ns)}", where)
    if np.any(np.diff(t_ns) <= 0):
        raise DataError("pose timestamps are not strictly increasing", where)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise DataError("non-finite poses", where)

    t_first, t_last = t_ns[0] * 1e-9, t_ns[-1] * 1e-9
    w0 = t_first if start is None else max(float(start), t_first)
    w1 = t_last if duration is None else min(w0 + float(duration), t_last)
    if start is not None and float(start) > t_last:
        raise DataError(f"start {start} s is after the last pose ({t_last:.6f} s)", where)
    if w1 - w0 <= 0:
        raise DataError(f"empty window [{w0}, {w1}] s", where)

    t = t_ns * 1e-9
    keep = (t >= w0 - config.edge_padding) & (t <= w1 + config.edge_padding)
    t_ns, pos, quat = t_ns[keep], pos[keep], quat[keep]
    poses = len(t_ns)
    quat = sign_continuous(quat / np.linalg.norm(quat, axis=1, keepdims=True))
    period = typical_period(t_ns * 1e-9) if poses > 1 else 0.0
    merged = dropped = 0
    if config.merge_fraction > 0 and poses > 1:
        floor = 0.0 if config.jump_threshold is None else config.jump_threshold
        keep = drop_inconsistent_duplicates(t_ns, pos, config.merge_fraction * period, floor)
        dropped = int(np.count_nonzero(~keep))
        if dropped:
            t_ns, pos, quat = t_ns[keep], pos[keep], quat[keep]
            name_ = "" if where is None else f"{where}: "
            warnings.warn(f"{name_}dropped {dropped} of {poses} poses stamped within "
                          f"{config.merge_fraction * period * 1e3:.2g} ms of another that "
                          "they disagree with by more than the noise and the motion allow "
                          "(timestamp jitter)", DataRepairWarning, stacklevel=2)
        t_ns, pos, quat, merged = merge_near_duplicates(t_ns, pos, quat,
                                                        config.merge_fraction * period)
    if len(t_ns) < 2 * (DEGREE + 1):
        raise DataError(f"only {len(t_ns)} poses in the window [{w0}, {w1}] s", where)

    t_ref_ns = int(t_ns[0])
    tau = (t_ns - t_ref_ns).astype(np.float64) * 1e-9
    jumps = np.zeros(0, dtype=np.int64)
    if config.jump_threshold is not None:
        pos, jumps = remove_position_jumps(tau, pos, config.jump_threshold, config.jump_sigmas,
                                           config.jump_max_jerk, config.jump_ramp_acceleration)
    spacing = max(config.knot_spacing, config.min_samples_per_knot * period)
    knots = uniform_knots(tau[0], tau[-1], spacing)
    fit = _PenalisedFit(tau, time_weights(tau, period), knots)
    pos_noise = sample_noise(tau, pos, period)
    rot_noise = rotation_noise(tau, quat, period)
    if config.match_noise:
        lam_p, coef_p = _noise_matched(fit, pos, float(np.sum(pos_noise**2)), config.smoothing)
        # a small rotation of angle theta moves a unit quaternion by theta / 2
        lam_q, coef_q = _noise_matched(fit, quat, float(np.sum(rot_noise**2)) / 4.0,
                                       config.smoothing)
    else:
        lam_p = lam_q = config.smoothing
        coef_p, coef_q = fit.coefficients(pos, lam_p), fit.coefficients(quat, lam_q)
    traj = Trajectory(float(w0), float(w1), BSpline(knots, coef_p, DEGREE),
                      BSpline(knots, coef_q, DEGREE), t_ref_ns, name)

    # residuals at the poses inside the span (all of them for a span between two poses)
    inside = (tau >= w0 - traj.t_ref - 1e-6) & (tau <= w1 - traj.t_ref + 1e-6)
    inside |= not np.any(inside)
    dp = np.linalg.norm(traj.position_spline(tau[inside]) - pos[inside], axis=1)
    angle = _rotation_angle(traj.quaternion_spline(tau[inside]), quat[inside])
    report = FitReport(
        poses=int(poses), merged=int(merged), dropped=dropped, jumps=int(jumps.size),
        median_period_s=float(period), max_gap_s=float(np.max(np.diff(tau))),
        knot_spacing_s=float(knots[DEGREE + 1] - knots[DEGREE]),
        smoothing_position=float(lam_p), smoothing_rotation=float(lam_q),
        position_noise_m=float(np.linalg.norm(pos_noise)),
        rotation_noise_rad=float(np.linalg.norm(rot_noise)),
        position_residual_rms_m=float(np.sqrt(np.mean(dp**2))),
        rotation_residual_rms_rad=float(np.sqrt(np.mean(angle**2))),
        **motion_peaks(traj),
    )
    return traj, report


def fit_tum_trajectory(source: str | Path | GroundTruth, start: float | None = None,
                       duration: float | None = None,
                       config: FitConfig = FitConfig(),  # noqa: B008
                       where: str | Path | None = None) -> Trajectory:
    """:func:`fit_trajectory_report`'s trajectory alone (same arguments, errors and
    warnings)."""
    return fit_trajectory_report(source, start, duration, config, where)[0]


def check_flight_limits(report: FitReport, config: FitConfig = FitConfig(),  # noqa: B008
                        where: str | Path | None = None) -> None:
    """Warn or refuse when the fitted flight is beyond what a drone flies.

    Peaks above ``config.warn_*`` give one :class:`~uavcal_jax.errors.FlightLimitWarning`
    (one line naming the peaks and limits); above ``config.refuse_*`` a
    :class:`~uavcal_jax.errors.DataError` (``where``: the file, for the message).
    """
    f, w = report.peak_specific_force_mps2, report.peak_angular_rate_radps
    text = (f"peak specific force {f:.1f} m/s^2 ({f / GRAVITY:.1f} g), peak angular rate "
            f"{w:.1f} rad/s; the fit's position residual is "
            f"{report.position_residual_rms_m * 1e3:.2f} mm RMS")
    if f > config.refuse_specific_force or w > config.refuse_angular_rate:
        raise DataError(
            f"the fitted flight is not one a drone can fly: {text} (limits "
            f"{config.refuse_specific_force / GRAVITY:g} g, {config.refuse_angular_rate:g} "
            "rad/s); position steps, wrong units or wrong timestamps in the file?", where)
    if f > config.warn_specific_force or w > config.warn_angular_rate:
        name = "" if where is None else f"{where}: "
        warnings.warn(f"{name}the fitted flight exceeds what a drone flies: {text} (limits "
                      f"{config.warn_specific_force / GRAVITY:g} g, "
                      f"{config.warn_angular_rate:g} rad/s); its IMU will not look like a "
                      "real one", FlightLimitWarning, stacklevel=2)
