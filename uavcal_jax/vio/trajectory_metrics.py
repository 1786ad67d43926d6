"""Trajectory accuracy: ATE and RPE as evo computes them (the plot of estimate against truth is
:func:`uavcal_jax.plots.plot_trajectories`).

A trajectory is a :class:`~uavcal_jax.data.sequence.GroundTruth` (what
:func:`~uavcal_jax.data.tum.read_tum` returns; any object with ``t_ns``, ``position`` and
``quaternion`` works) or a tuple ``(t, p, q)``: ``t`` (N,) seconds as floats or int64
nanoseconds, ``p`` (N, 3) metres, ``q`` (N, 4) body-to-world rotation, (w, x, y, z).

Pipeline (that of ``evo_ape`` / ``evo_rpe``, so the figures equal evo's):

1. Association (:func:`associate`): each pose of the shorter trajectory is paired with the
   nearest-in-time pose of the other within ``max_diff_s``, as
   ``evo.core.sync.associate_trajectories(ground_truth, estimate)`` does; done here on exact
   int64 nanoseconds.
2. Alignment of the matched estimate onto the matched truth (:func:`align`): ``"se3"``
   (Umeyama, rotation and translation; the default, since stereo VIO observes metric scale),
   ``"sim3"`` (Umeyama with scale), ``"origin"`` (first poses made equal) or ``"none"``.
   Umeyama is evo's own ``evo.core.geometry.umeyama_alignment``.
3. Errors: ATE is the position error of the aligned estimate per matched pose; RPE compares
   relative poses of pose pairs a ``delta`` apart (in frames, or metres of travelled path),
   ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``, giving a translation part (metres) and a rotation
   angle (degrees).

Bad input (empty or non-finite poses, non-rotations, unordered times, no overlap, too few
matches to align, a ``delta`` that yields no pair) raises :class:`~uavcal_jax.errors.DataError`
saying which trajectory is at fault and why.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from evo.core.geometry import GeometryException, umeyama_alignment
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.tum import QUATERNION_NORM_TOLERANCE
from uavcal_jax.errors import DataError

#: Largest time difference (s) at which two poses are associated (evo's default).
DEFAULT_MAX_TIME_DIFF_S = 0.01
#: Alignment methods of :func:`align`; the first is the default.
ALIGNMENTS = ("se3", "sim3", "posyaw", "origin", "none")
#: Units of the RPE ``delta``.
RPE_UNITS = ("frames", "m")
#: Relative tolerance on a metric ``delta`` when searching all pairs (evo's ``rel_delta_tol``).
RPE_REL_DELTA_TOL = 0.1
#: Umeyama in 3-D needs at least this many matched positions (3 non-collinear points).
MIN_POSES_TO_ALIGN = 3


@dataclass(frozen=True)
class Statistics:
    """Summary of per-pose (ATE) or per-pair (RPE) errors, in the unit of the errors."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @classmethod
    def of(cls, errors: np.ndarray) -> Statistics:
        """Statistics of a non-empty (K,) error array (``std`` is the population std, as evo)."""
        e = np.asarray(errors, dtype=np.float64)
        return cls(rmse=float(np.sqrt(np.mean(e * e))), mean=float(np.mean(e)),
                   median=float(np.median(e)), std=float(np.std(e)), min=float(np.min(e)),
                   max=float(np.max(e)), count=int(e.size))

    def as_dict(self) -> dict[str, float | int]:
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std,
                "min": self.min, "max": self.max, "count": self.count}


@dataclass(frozen=True)
class Alignment:
    """``x_ref = scale * rotation @ x_est + translation`` (scale 1 except for ``"sim3"``).

    Orientations map as ``R_ref = rotation @ R_est``.
    """

    method: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error.

    Attributes:
        translation: statistics of ``errors`` (metres).
        errors: (M,) position error of each matched pose after alignment, metres.
        aligned: the matched estimate after alignment (M poses; write it with ``write_tum``).
        reference: the matched ground truth (M poses, same times as ``aligned``'s pairs).
        alignment: the transform applied to the estimate.
    """

    translation: Statistics
    errors: np.ndarray
    aligned: GroundTruth
    reference: GroundTruth
    alignment: Alignment

    def as_dict(self) -> dict[str, Any]:
        return {"alignment": self.alignment.method, "scale": self.alignment.scale,
                "translation_m": self.translation.as_dict()}


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over pose pairs ``delta`` apart.

    Attributes:
        translation: statistics of ``translation_errors`` (metres).
        rotation: statistics of ``rotation_errors`` (degrees).
        translation_errors: (K,) norm of the relative error's translation, metres.
        rotation_errors: (K,) angle of the relative error's rotation, degrees.
        pairs: (K, 2) indices ``(i, j)`` into the matched (aligned) trajectories.
    """

    translation: Statistics
    rotation: Statistics
    translation_errors: np.ndarray
    rotation_errors: np.ndarray
    pairs: np.ndarray
    delta: float
    unit: str
    alignment: Alignment

    def as_dict(self) -> dict[str, Any]:
        return {"delta": self.delta, "unit": self.unit, "alignment": self.alignment.method,
                "translation_m": self.translation.as_dict(),
                "rotation_deg": self.rotation.as_dict()}


def as_trajectory(trajectory: Any, what: str = "trajectory") -> GroundTruth:
    """Validate a trajectory (see the module docstring) and return it as ``GroundTruth``.

    ``what`` names the trajectory in error messages ("estimate", "ground truth").
    """
    if isinstance(trajectory, tuple | list):
        if len(trajectory) != 3:
            raise DataError(f"{what}: expected (t, p, q), got a sequence of {len(trajectory)}")
        t, p, q = (np.asarray(a) for a in trajectory)
        t_ns = t.astype(np.int64) if np.issubdtype(t.dtype, np.integer) \
            else np.round(t.astype(np.float64) * 1e9).astype(np.int64)
    elif all(hasattr(trajectory, a) for a in ("t_ns", "position", "quaternion")):
        t, p, q = trajectory.t_ns, trajectory.position, trajectory.quaternion
        t_ns = np.asarray(t).astype(np.int64)
    else:
        raise DataError(f"{what}: expected GroundTruth or (t, p, q), got "
                        f"{type(trajectory).__name__}")
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    n = t_ns.shape[0] if t_ns.ndim == 1 else -1
    if n < 0 or p.shape != (n, 3) or q.shape != (n, 4):
        raise DataError(f"{what}: shapes disagree: t {t_ns.shape}, position {p.shape}, "
                        f"quaternion {q.shape} (want (N,), (N, 3), (N, 4))")
    if n == 0:
        raise DataError(f"{what} is empty (no poses)")
    bad = np.flatnonzero(~(np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1)))
    if bad.size:
        raise DataError(f"{what}: pose {bad[0]} (t={t_ns[bad[0]] * 1e-9:.9f} s) is not finite "
                        f"(NaN or inf; {bad.size} such poses)")
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        raise DataError(f"{what}: quaternion {bad[0]} has norm {norm[bad[0]]:.6g}, not 1 "
                        f"({bad.size} such poses)")
    back = np.flatnonzero(np.diff(t_ns) <= 0)
    if back.size:
        raise DataError(f"{what}: timestamps not strictly increasing at pose {back[0] + 1}")
    return GroundTruth(t_ns=t_ns, position=p, quaternion=q)


def _take(traj: GroundTruth, idx: np.ndarray) -> GroundTruth:
    return GroundTruth(t_ns=traj.t_ns[idx], position=traj.position[idx],
                       quaternion=traj.quaternion[idx])


def _rotations(traj: GroundTruth) -> Rotation:
    return Rotation.from_quat(traj.quaternion[:, [1, 2, 3, 0]])


def _nearest(short: np.ndarray, long: np.ndarray, max_diff_ns: int) -> tuple[np.ndarray, ...]:
    """evo's ``matching_time_indices`` on sorted int64 stamps: nearest, ties to the earlier."""
    hi = np.searchsorted(long, short, side="right").clip(max=long.size - 1)
    lo = (hi - 1).clip(min=0)
    d_hi = np.abs(long[hi] - short)
    d_lo = np.where(hi > 0, np.abs(short - long[lo]), np.iinfo(np.int64).max)
    best = np.where(d_hi < d_lo, hi, lo)
    ok = np.minimum(d_hi, d_lo) <= max_diff_ns
    return np.flatnonzero(ok), best[ok]


def associate(estimate: Any, ground_truth: Any, *, max_diff_s: float = DEFAULT_MAX_TIME_DIFF_S
              ) -> tuple[GroundTruth, GroundTruth]:
    """Pair poses by nearest timestamp within ``max_diff_s`` seconds.

    Returns:
        ``(estimate, ground_truth)`` restricted to the M matched pairs, in time order of the
        shorter trajectory (a pose of the longer one may serve two pairs, as in evo).
    """
    est = as_trajectory(estimate, "estimate")
    gt = as_trajectory(ground_truth, "ground truth")
    max_diff_ns = int(round(max_diff_s * 1e9))
    # evo starts from the shorter trajectory (the estimate when lengths are equal).
    est_is_short = len(gt) >= len(est)
    short, long = (est, gt) if est_is_short else (gt, est)
    i_short, i_long = _nearest(short.t_ns, long.t_ns, max_diff_ns)
    if i_short.size == 0:
        raise DataError(
            f"no estimate timestamp within {max_diff_s:g} s of a ground-truth timestamp "
            f"(estimate spans {est.t[0]:.3f}..{est.t[-1]:.3f} s, ground truth "
            f"{gt.t[0]:.3f}..{gt.t[-1]:.3f} s)")
    i_est, i_gt = (i_short, i_long) if est_is_short else (i_long, i_short)
    return _take(est, i_est), _take(gt, i_gt)


def align(estimate: GroundTruth, reference: GroundTruth, method: str = ALIGNMENTS[0]
          ) -> Alignment:
    """Transform taking the matched ``estimate`` onto the matched ``reference`` (same length).

    ``"se3"``/``"sim3"`` minimise the summed squared position error (Umeyama, evo's code);
    ``"posyaw"`` minimises it over a yaw about z and a translation only, the four directions a
    VIO cannot observe when both worlds are gravity-aligned with z up (Zhang and Scaramuzza,
    IROS 2018, rpg_trajectory_evaluation's ``posyaw``): unlike SE(3) it stays determined along
    a straight, non-vertical flight, where Umeyama may roll the estimate about the line and
    carry anything off the line (a located target) metres away; ``"origin"`` makes the first
    poses coincide; ``"none"`` is the identity.
    """
    if method not in ALIGNMENTS:
        raise ValueError(f"alignment must be one of {ALIGNMENTS}, got {method!r}")
    if method == "none":
        return Alignment(method, np.eye(3), np.zeros(3), 1.0)
    if method == "origin":
        r = (_rotations(reference)[0] * _rotations(estimate)[0].inv()).as_matrix()
        t = reference.position[0] - r @ estimate.position[0]
        return Alignment(method, r, t, 1.0)
    if method == "posyaw":
        return _align_posyaw(estimate.position, reference.position)
    if len(estimate) < MIN_POSES_TO_ALIGN:
        raise DataError(f"{method} Umeyama alignment needs at least {MIN_POSES_TO_ALIGN} matched "
                        f"poses, got {len(estimate)}")
    try:
        r, t, s = umeyama_alignment(estimate.position.T, reference.position.T,
                                    method == "sim3")
    except GeometryException as exc:
        raise DataError(f"{method} alignment impossible: the {len(estimate)} matched positions "
                        f"are degenerate (collinear or identical): {exc}") from exc
    return Alignment(method, np.asarray(r), np.asarray(t), float(s))


#: Below this spread of the horizontal positions (m^2, mean squared distance from their centre:
#: 0.5 m RMS) a yaw fitted to positions is left to the noise (a hover, a vertical climb, a short
#: hop): a centimetre of drift over a 20 cm path is 3 degrees of yaw, 0.25 m of error for a
#: target 4 m away (measured on a 2 s flight: 0.33 m, against 0.07 m aligned at the first pose).
MIN_POSYAW_SPREAD_M2 = 0.25


def _align_posyaw(estimate: np.ndarray, reference: np.ndarray) -> Alignment:
    """The least-squares yaw about z and translation taking ``estimate`` (M, 3) onto
    ``reference`` (M, 3): with both centred, yaw = atan2(sum(e x r)_z, sum(e_xy . r_xy))."""
    e = estimate - estimate.mean(axis=0)
    r = reference - reference.mean(axis=0)
    if len(e) < MIN_POSES_TO_ALIGN or np.mean(np.sum(e[:, :2] ** 2, axis=1)) < \
            MIN_POSYAW_SPREAD_M2:
        raise DataError(f"posyaw alignment impossible: the {len(e)} matched positions do not "
                        "spread horizontally (a hover or a vertical flight)")
    yaw = np.arctan2(np.sum(e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0]),
                     np.sum(e[:, 0] * r[:, 0] + e[:, 1] * r[:, 1]))
    rot = Rotation.from_euler("z", yaw).as_matrix()
    t = reference.mean(axis=0) - rot @ estimate.mean(axis=0)
    return Alignment("posyaw", rot, t, 1.0)


def apply_alignment(traj: GroundTruth, alignment: Alignment) -> GroundTruth:
    """``traj`` with every pose mapped by ``alignment`` (positions scaled, then transformed)."""
    a = alignment
    p = a.scale * traj.position @ a.rotation.T + a.translation
    q = (Rotation.from_matrix(a.rotation) * _rotations(traj)).as_quat()[:, [3, 0, 1, 2]]
    # One hemisphere for the output (w >= 0): the same rotations, stable files and plots.
    q = np.where(q[:, :1] < 0.0, -q, q)
    return GroundTruth(t_ns=traj.t_ns, position=p, quaternion=q)


def _matched_aligned(estimate, ground_truth, alignment, max_diff_s):
    est, gt = associate(estimate, ground_truth, max_diff_s=max_diff_s)
    a = align(est, gt, alignment)
    return apply_alignment(est, a), gt, a


def ate(estimate: Any, ground_truth: Any, *, alignment: str = ALIGNMENTS[0],
        max_diff_s: float = DEFAULT_MAX_TIME_DIFF_S) -> AteResult:
    """Absolute trajectory error (translation, metres) after association and alignment.

    Equals ``evo.main_ape.ape(gt, est, PoseRelation.translation_part, align=...,
    correct_scale=...)`` on ``associate_trajectories(gt, est, max_diff=max_diff_s)``.
    """
    est, gt, a = _matched_aligned(estimate, ground_truth, alignment, max_diff_s)
    errors = np.linalg.norm(est.position - gt.position, axis=1)
    return AteResult(Statistics.of(errors), errors, est, gt, a)


def _pairs_by_path(position: np.ndarray, delta: float, all_pairs: bool) -> list[tuple[int, int]]:
    """evo's ``filter_pairs_by_path``: pairs whose travelled path is ``delta`` metres."""
    steps = np.linalg.norm(np.diff(position, axis=0), axis=1)
    if all_pairs:
        dist = np.concatenate([[0.0], np.cumsum(steps)])
        tol = delta * RPE_REL_DELTA_TOL
        pairs = []
        for i in range(dist.size - 1):
            off = np.abs(dist[i + 1:] - dist[i] - delta)
            k = int(np.argmin(off))
            if off[k] <= tol:
                pairs.append((i, i + 1 + k))
        return pairs
    # Consecutive pairs: the path restarts at each chosen pose (sequential by nature).
    ids, path = [0], 0.0
    for i, step in enumerate(steps.tolist(), start=1):
        path += step
        if path >= delta:
            ids.append(i)
            path = 0.0
    return list(zip(ids, ids[1:], strict=False))


def _pairs(position: np.ndarray, delta: float, unit: str, all_pairs: bool) -> np.ndarray:
    n = position.shape[0]
    if unit == "frames":
        if all_pairs:
            i = np.arange(max(n - int(delta), 0))
            return np.stack([i, i + int(delta)], axis=1)
        ids = np.arange(0, n, int(delta))
        return np.stack([ids[:-1], ids[1:]], axis=1)
    return np.array(_pairs_by_path(position, delta, all_pairs), dtype=np.int64).reshape(-1, 2)


def rpe(estimate: Any, ground_truth: Any, *, delta: float = 1, unit: str = "frames",
        alignment: str = ALIGNMENTS[0], max_diff_s: float = DEFAULT_MAX_TIME_DIFF_S,
        all_pairs: bool = False, pairs_from_reference: bool = False) -> RpeResult:
    """Relative pose error over pairs ``delta`` frames (integer) or metres of path apart.

    Pairs are consecutive (``0-d, d-2d, ...``) unless ``all_pairs``; with metres, the path is
    that of the aligned estimate unless ``pairs_from_reference``. Equals
    ``evo.main_rpe.rpe(gt, est, PoseRelation.translation_part`` (and ``rotation_angle_deg``),
    ``delta=..., delta_unit=Unit.frames|meters, ...)`` on evo-associated trajectories.
    """
    if unit not in RPE_UNITS:
        raise ValueError(f"RPE unit must be one of {RPE_UNITS}, got {unit!r}")
    if not delta > 0 or (unit == "frames" and float(delta) != int(delta)):
        raise ValueError(f"RPE delta must be positive (an integer for frames), got {delta!r}")
    est, gt, a = _matched_aligned(estimate, ground_truth, alignment, max_diff_s)
    pairs = _pairs((gt if pairs_from_reference else est).position, delta, unit, all_pairs)
    if pairs.shape[0] == 0:
        raise DataError(f"RPE delta {delta:g} {unit} yields no pose pair among {len(est)} "
                        "matched poses (use a smaller delta)")
    i, j = pairs[:, 0], pairs[:, 1]
    r_est, r_gt = _rotations(est), _rotations(gt)
    t_est = r_est[i].inv().apply(est.position[j] - est.position[i])
    t_gt = r_gt[i].inv().apply(gt.position[j] - gt.position[i])
    # E = Q_rel^-1 P_rel: its translation is R_Qrel^T (t_P - t_Q), whose norm is |t_P - t_Q|.
    trans = np.linalg.norm(t_est - t_gt, axis=1)
    rel_gt = r_gt[i].inv() * r_gt[j]
    rel_est = r_est[i].inv() * r_est[j]
    rot = np.rad2deg((rel_gt.inv() * rel_est).magnitude())
    return RpeResult(Statistics.of(trans), Statistics.of(rot), trans, rot, pairs,
                     float(delta), unit, a)


def trajectory_errors(estimate: Any, ground_truth: Any, rpe_delta_m: float = 1.0) -> dict:
    """ATE and RPE as a JSON-able summary, for the CLI and the experiments.

    SE(3) alignment; a flight along a line (or a hover) leaves it undetermined, and then the
    trajectories are aligned at their first pose instead (``"alignment": "origin"``). RPE over
    ``rpe_delta_m`` metres of path is ``None`` when the path is shorter.
    """
    try:
        a = ate(estimate, ground_truth)
        alignment = "se3"
    except DataError:
        a = ate(estimate, ground_truth, alignment="origin")
        alignment = "origin"
    out = {"ate_m": {"rmse": a.translation.rmse, "mean": a.translation.mean,
                     "max": a.translation.max, "matched": a.translation.count,
                     "alignment": alignment}}
    try:
        r = rpe(estimate, ground_truth, delta=rpe_delta_m, unit="m", alignment=alignment)
        out["rpe_1m"] = {"translation_rmse_m": r.translation.rmse,
                         "rotation_rmse_deg": r.rotation.rmse}
    except DataError:
        out["rpe_1m"] = None
    return out
