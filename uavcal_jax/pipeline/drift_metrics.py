"""How far an estimated trajectory drifts from the truth as the flight goes on: the position
error against the distance travelled (the calibrator paper's section 5 question).

A trajectory is what :mod:`uavcal_jax.vio.trajectory_metrics` takes (a
:class:`~uavcal_jax.data.sequence.GroundTruth`: ``t_ns`` int64, ``position`` (N, 3) world
metres, ``quaternion`` (N, 4) body-to-world w, x, y, z). Drift is measured from the start:

* a dead-reckoned trajectory starts from the true state, so it is compared as it is
  (``align_m=None``);
* a VIO's world frame is gravity-aligned but its heading and origin are its own, so it is
  first turned about the vertical and shifted (4 degrees of freedom, never tilted: a tilt
  would hide a gravity error) to fit the truth over the first ``align_m`` metres travelled
  (:func:`start_alignment`), and then left alone: the error at the end is what accumulated
  along the flight, not an error spread over it as the whole-trajectory (SE(3)) alignment of
  the ATE does.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.errors import DataError
from uavcal_jax.vio.trajectory_metrics import Alignment, apply_alignment, associate

__all__ = ["DEFAULT_ALIGN_M", "drift_curve", "path_length", "start_alignment"]

#: Metres of travelled path over which a VIO trajectory is aligned to the truth.
DEFAULT_ALIGN_M = 10.0
# below this spread (m) the positions cannot fix a heading; the first poses' headings do
_MIN_SPREAD_M = 1.0


def path_length(position: np.ndarray) -> np.ndarray:
    """``(N,)`` metres travelled up to each of ``position`` ``(N, 3)`` (0 at the first)."""
    step = np.linalg.norm(np.diff(np.asarray(position, np.float64), axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _yaw(R: np.ndarray) -> float:
    """The rotation about world z closest (Frobenius) to ``R`` (3, 3), radians."""
    return float(np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))


def start_alignment(estimate, reference, align_m: float = DEFAULT_ALIGN_M) -> Alignment:
    """The heading-and-offset transform fitting the matched ``estimate`` onto the matched
    ``reference`` (same length, :func:`~uavcal_jax.vio.trajectory_metrics.associate`) over
    the poses whose reference path length is at most ``align_m`` metres.

    Heading by 2-D Procrustes of the centred horizontal positions; when they spread less than
    1 m (a hover), from the first poses' orientations instead. Translation from the centroids.
    """
    dist = path_length(reference.position)
    keep = dist <= align_m
    keep[: min(3, len(keep))] = True
    e, r = estimate.position[keep], reference.position[keep]
    ec, rc = e - e.mean(0), r - r.mean(0)
    if np.sqrt(np.mean(np.sum(rc[:, :2] ** 2, axis=1))) >= _MIN_SPREAD_M:
        yaw = float(np.arctan2(np.sum(ec[:, 0] * rc[:, 1] - ec[:, 1] * rc[:, 0]),
                               np.sum(ec[:, 0] * rc[:, 0] + ec[:, 1] * rc[:, 1])))
    else:
        R_r = Rotation.from_quat(reference.quaternion[0, [1, 2, 3, 0]]).as_matrix()
        R_e = Rotation.from_quat(estimate.quaternion[0, [1, 2, 3, 0]]).as_matrix()
        yaw = _yaw(R_r @ R_e.T)
    R = Rotation.from_euler("z", yaw).as_matrix()
    return Alignment("start-yaw", R, r.mean(0) - R @ e.mean(0), 1.0)


def drift_curve(estimate, ground_truth, *, align_m: float | None = DEFAULT_ALIGN_M
                ) -> dict[str, np.ndarray]:
    """The position error of ``estimate`` against the distance travelled along
    ``ground_truth``.

    Args:
        estimate, ground_truth: trajectories (associated here by nearest time, 10 ms).
        align_m: align over the first this many metres (:func:`start_alignment`), or ``None``
            to compare as is (a trajectory that starts from the true state).

    Returns:
        ``t_ns`` (M,), ``distance_m`` (M,) travelled along the truth, ``error_m`` (M,)
        position error; the matched poses only.

    Raises:
        DataError: no pose of ``estimate`` matches the truth.
    """
    est, gt = associate(estimate, ground_truth)
    if len(est) == 0:
        raise DataError("no estimated pose matches the ground truth")
    if align_m is not None:
        est = apply_alignment(est, start_alignment(est, gt, align_m))
    return {"t_ns": np.asarray(gt.t_ns, np.int64), "distance_m": path_length(gt.position),
            "error_m": np.linalg.norm(est.position - gt.position, axis=1)}
