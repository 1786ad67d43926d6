"""ATE / RPE of uavcal_jax.vio.trajectory_metrics against evo's own pipeline (evo_ape, evo_rpe)."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import sync
from evo.core.metrics import PoseRelation, Unit
from evo.core.trajectory import PoseTrajectory3D
from evo.main_ape import ape as evo_ape
from evo.main_rpe import rpe as evo_rpe
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc import read_ground_truth_csv
from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.errors import DataError
from uavcal_jax.vio import trajectory_metrics as tm

STATS = ("rmse", "mean", "median", "std", "min", "max")
ATOL = 1e-6


def _wxyz(r: Rotation) -> np.ndarray:
    q = r.as_quat()[:, [3, 0, 1, 2]]
    return np.where(q[:, :1] < 0, -q, q)


def _synthetic_truth(n: int = 300, rate_hz: float = 20.0) -> GroundTruth:
    """A figure-eight flight with heading along the velocity and a little roll and pitch."""
    t_ns = np.arange(n, dtype=np.int64) * int(1e9 / rate_hz) + 1_000_000_000
    s = np.linspace(0.0, 2.0 * np.pi, n)
    p = np.stack([3.0 * np.sin(s), 1.5 * np.sin(2.0 * s), 1.0 + 0.4 * np.sin(3.0 * s)], axis=1)
    yaw = np.unwrap(np.arctan2(np.gradient(p[:, 1]), np.gradient(p[:, 0])))
    euler = np.stack([0.1 * np.sin(5.0 * s), 0.08 * np.cos(4.0 * s), yaw], axis=1)
    q = _wxyz(Rotation.from_euler("xyz", euler))
    return GroundTruth(t_ns=t_ns, position=p, quaternion=q)


def _perturb(gt: GroundTruth, rng, *, sigma_p: float, sigma_r: float, scale: float = 1.0,
             dt_ns: int = 0) -> tuple[GroundTruth, Rotation, np.ndarray]:
    """``gt`` seen in another frame (unknown rigid transform, optional scale) plus noise."""
    r_off = Rotation.from_rotvec([0.3, -0.2, 1.1])
    t_off = np.array([5.0, -2.0, 0.7])
    p = scale * (r_off.apply(gt.position) + t_off) + rng.normal(0.0, sigma_p, gt.position.shape)
    noise = Rotation.from_rotvec(rng.normal(0.0, sigma_r, gt.position.shape))
    r = r_off * Rotation.from_quat(gt.quaternion[:, [1, 2, 3, 0]]) * noise
    est = GroundTruth(t_ns=gt.t_ns + dt_ns, position=p, quaternion=_wxyz(r))
    return est, r_off, t_off


def _evo(traj: GroundTruth) -> PoseTrajectory3D:
    return PoseTrajectory3D(positions_xyz=traj.position, orientations_quat_wxyz=traj.quaternion,
                            timestamps=traj.t_ns * 1e-9)


def _evo_pair(est: GroundTruth, gt: GroundTruth):
    return sync.associate_trajectories(_evo(gt), _evo(est), max_diff=tm.DEFAULT_MAX_TIME_DIFF_S)


def _evo_kwargs(alignment: str) -> dict:
    return {"se3": {"align": True}, "sim3": {"align": True, "correct_scale": True},
            "origin": {"align_origin": True}, "none": {}}[alignment]


def _check(ours: tm.Statistics, errors: np.ndarray, result) -> None:
    np.testing.assert_allclose(errors, result.np_arrays["error_array"], rtol=0, atol=ATOL)
    for k in STATS:
        assert getattr(ours, k) == pytest.approx(result.stats[k], rel=0, abs=ATOL), k
    assert ours.count == result.np_arrays["error_array"].size


def _compare_ate(est, gt, alignment):
    ref_e, est_e = _evo_pair(est, gt)
    ours = tm.ate(est, gt, alignment=alignment)
    theirs = evo_ape(ref_e, est_e, PoseRelation.translation_part, **_evo_kwargs(alignment))
    _check(ours.translation, ours.errors, theirs)
    # The aligned estimate is the one evo evaluates, pose by pose.
    np.testing.assert_allclose(ours.aligned.position, est_e.positions_xyz, rtol=0, atol=1e-9)
    return ours


def _compare_rpe(est, gt, alignment, **kw):
    ours = tm.rpe(est, gt, alignment=alignment, **kw)
    evo_kw = {"delta": kw.get("delta", 1),
              "delta_unit": Unit.meters if kw.get("unit") == "m" else Unit.frames,
              "all_pairs": kw.get("all_pairs", False),
              "pairs_from_reference": kw.get("pairs_from_reference", False),
              "rel_delta_tol": tm.RPE_REL_DELTA_TOL, **_evo_kwargs(alignment)}
    for relation, stats, errors in (
            (PoseRelation.translation_part, ours.translation, ours.translation_errors),
            (PoseRelation.rotation_angle_deg, ours.rotation, ours.rotation_errors)):
        ref_e, est_e = _evo_pair(est, gt)
        _check(stats, errors, evo_rpe(ref_e, est_e, relation, **evo_kw))
    return ours


RPE_CASES = [
    {"delta": 1}, {"delta": 7}, {"delta": 7, "all_pairs": True},
    {"delta": 1.0, "unit": "m"}, {"delta": 1.0, "unit": "m", "all_pairs": True},
    {"delta": 1.0, "unit": "m", "pairs_from_reference": True},
]


#: The alignments evo has (posyaw is rpg_trajectory_evaluation's; tested on its own below).
EVO_ALIGNMENTS = [a for a in tm.ALIGNMENTS if a != "posyaw"]


@pytest.mark.parametrize("alignment", EVO_ALIGNMENTS)
def test_synthetic_matches_evo_and_noise_level(alignment):
    rng = np.random.default_rng(0)
    gt = _synthetic_truth()
    sigma = 0.02
    est, r_off, t_off = _perturb(gt, rng, sigma_p=sigma, sigma_r=0.002)
    result = _compare_ate(est, gt, alignment)
    for case in RPE_CASES:
        _compare_rpe(est, gt, alignment, **case)
    if alignment == "se3":
        # Alignment removes the injected transform; what is left is the injected noise:
        # the RMSE of a 3-D Gaussian is sigma * sqrt(3) (900 samples: a few percent spread).
        assert result.translation.rmse == pytest.approx(sigma * np.sqrt(3.0), rel=0.08)
        a = result.alignment
        assert (Rotation.from_matrix(a.rotation) * r_off).magnitude() < 1e-3
        np.testing.assert_allclose(a.rotation @ t_off + a.translation, 0.0, atol=5e-3)
    if alignment == "none":
        assert result.translation.min > 1.0  # the unknown transform is not removed


def test_posyaw_recovers_yaw_and_translation_on_a_straight_leg():
    """A straight, level leg seen in a frame yawed by 0.7 rad and shifted: posyaw recovers the
    transform (the least-squares yaw, checked against a brute-force search), so a point 8 m off
    the line maps where it belongs; SE(3) only fits the line and may roll about it."""
    rng = np.random.default_rng(3)
    n = 200
    t_ns = np.arange(n, dtype=np.int64) * 50_000_000
    p = np.stack([np.linspace(0.0, 6.0, n), np.linspace(0.0, -3.0, n), np.full(n, 1.5)], axis=1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    gt = GroundTruth(t_ns=t_ns, position=p, quaternion=q)
    r_off, t_off = Rotation.from_euler("z", 0.7), np.array([2.0, -1.0, 0.3])
    est = GroundTruth(t_ns=t_ns, position=r_off.apply(p) + t_off
                      + rng.normal(0.0, 0.005, p.shape), quaternion=q)
    result = tm.ate(est, gt, alignment="posyaw")
    a = result.alignment
    assert a.method == "posyaw" and a.scale == 1.0
    yaw = Rotation.from_matrix(a.rotation).as_euler("xyz")
    np.testing.assert_allclose(yaw[:2], 0.0, atol=1e-12)  # a rotation about z only
    grid = np.linspace(-np.pi, np.pi, 20001)
    e, r = est.position - est.position.mean(0), gt.position - gt.position.mean(0)
    cost = [np.sum((Rotation.from_euler("z", g).apply(e) - r) ** 2) for g in grid]
    assert yaw[2] == pytest.approx(grid[int(np.argmin(cost))], abs=5e-4)
    assert yaw[2] == pytest.approx(-0.7, abs=5e-3)
    off_line = np.array([-0.7, -7.7, -0.5])  # a target seen beside the leg
    mapped = a.rotation @ (r_off.apply(off_line) + t_off) + a.translation
    np.testing.assert_allclose(mapped, off_line, atol=0.05)
    assert result.translation.rmse < 0.02
    hover = GroundTruth(t_ns=t_ns, position=np.tile([0.0, 0.0, 1.0], (n, 1)), quaternion=q)
    with pytest.raises(DataError, match="posyaw"):
        tm.ate(hover, hover, alignment="posyaw")


def test_sim3_recovers_scale():
    rng = np.random.default_rng(1)
    gt = _synthetic_truth()
    est, _, _ = _perturb(gt, rng, sigma_p=0.005, sigma_r=0.001, scale=1.7)
    result = _compare_ate(est, gt, "sim3")
    assert result.alignment.scale == pytest.approx(1.0 / 1.7, rel=1e-3)
    assert result.translation.rmse == pytest.approx(0.005 / 1.7 * np.sqrt(3.0), rel=0.1)
    # SE(3) cannot absorb the scale: its error is the 70 % scale error of the whole flight.
    assert tm.ate(est, gt).translation.rmse > 50 * result.translation.rmse
    _compare_rpe(est, gt, "sim3", delta=1.0, unit="m")


def test_real_euroc_ground_truth_with_association(euroc_micro):
    gt = read_ground_truth_csv(euroc_micro / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    rng = np.random.default_rng(2)
    # The 20 Hz truth, 30 % of it dropped, stamped 1.3 ms late, plus poses no truth is near
    # (halfway between truth stamps, and past its end): association must pick and skip them.
    keep = np.sort(rng.choice(len(gt), size=len(gt) * 7 // 10, replace=False))
    sub = GroundTruth(t_ns=gt.t_ns[keep], position=gt.position[keep],
                      quaternion=gt.quaternion[keep])
    est, _, _ = _perturb(sub, rng, sigma_p=0.01, sigma_r=0.003, dt_ns=1_300_000)
    far = np.concatenate([gt.t_ns[rng.choice(len(gt) - 1, 20, replace=False)] + 25_000_000,
                          gt.t_ns[-1] + 20_000_000 + np.arange(5) * 50_000_000])
    pick = rng.integers(0, len(est), far.size)
    t_ns = np.concatenate([est.t_ns, far])
    order = np.argsort(t_ns)
    est = GroundTruth(t_ns=t_ns[order],
                      position=np.concatenate([est.position, est.position[pick]])[order],
                      quaternion=np.concatenate([est.quaternion, est.quaternion[pick]])[order])
    m_est, m_gt = tm.associate(est, gt)
    ref_e, est_e = _evo_pair(est, gt)
    np.testing.assert_array_equal(m_gt.t_ns * 1e-9, ref_e.timestamps)
    np.testing.assert_array_equal(m_est.t_ns * 1e-9, est_e.timestamps)
    assert len(m_est) == len(keep) < len(est)
    for alignment in ("se3", "sim3"):
        _compare_ate(est, gt, alignment)
        _compare_rpe(est, gt, alignment, delta=5)
        _compare_rpe(est, gt, alignment, delta=0.5, unit="m")
    # The other branch of evo's association: here the truth is the shorter trajectory.
    sparse_gt = GroundTruth(t_ns=gt.t_ns[::4], position=gt.position[::4],
                            quaternion=gt.quaternion[::4])
    _compare_ate(est, sparse_gt, "se3")
    _compare_rpe(est, sparse_gt, "se3", delta=2)


def test_arrays_in_seconds_equal_ground_truth_input():
    gt = _synthetic_truth(60)
    est, _, _ = _perturb(gt, np.random.default_rng(3), sigma_p=0.01, sigma_r=0.001)
    as_arrays = (est.t_ns * 1e-9, est.position, est.quaternion)
    assert tm.ate(as_arrays, gt).translation == tm.ate(est, gt).translation


def test_bad_input_raises_data_error():
    gt = _synthetic_truth(40)
    est, _, _ = _perturb(gt, np.random.default_rng(4), sigma_p=0.01, sigma_r=0.001)
    empty = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    with pytest.raises(DataError, match="estimate is empty"):
        tm.ate(empty, gt)
    with pytest.raises(DataError, match="ground truth is empty"):
        tm.rpe(est, empty)
    late = GroundTruth(t_ns=est.t_ns + 100_000_000_000, position=est.position,
                       quaternion=est.quaternion)
    with pytest.raises(DataError, match="no estimate timestamp within 0.01 s"):
        tm.ate(late, gt)
    p = est.position.copy()
    p[7, 1] = np.nan
    with pytest.raises(DataError, match=r"estimate: pose 7 .* not finite"):
        tm.ate((est.t_ns, p, est.quaternion), gt)
    q = gt.quaternion.copy()
    q[3] = np.inf
    with pytest.raises(DataError, match=r"ground truth: pose 3 .* not finite"):
        tm.ate(est, (gt.t_ns, gt.position, q))
    two = (est.t_ns[:2], est.position[:2], est.quaternion[:2])
    with pytest.raises(DataError, match="at least 3 matched poses, got 2"):
        tm.ate(two, gt)
    line = (gt.t_ns[:5], np.outer(np.arange(5.0), [1.0, 0.0, 0.0]), gt.quaternion[:5])
    with pytest.raises(DataError, match="degenerate"):
        tm.ate(line, line)
    with pytest.raises(DataError, match="not strictly increasing"):
        tm.ate((est.t_ns[::-1], est.position, est.quaternion), gt)
    with pytest.raises(DataError, match="norm"):
        tm.ate((est.t_ns, est.position, 2.0 * est.quaternion), gt)
    with pytest.raises(DataError, match="yields no pose pair"):
        tm.rpe(est, gt, delta=100.0, unit="m")
    with pytest.raises(ValueError, match="alignment must be one of"):
        tm.ate(est, gt, alignment="sim2")


def test_plot_writes_png(tmp_path):
    import matplotlib.image

    from uavcal_jax.plots import plot_trajectories

    gt = _synthetic_truth(120)
    est, _, _ = _perturb(gt, np.random.default_rng(5), sigma_p=0.03, sigma_r=0.001)
    path = plot_trajectories(est, gt, tmp_path / "plots" / "traj.png", title="synthetic")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (480, 1100)
    # Not blank: many distinct colours (two curves, axes, text on white).
    assert np.unique(image.reshape(-1, image.shape[-1]), axis=0).shape[0] > 50
