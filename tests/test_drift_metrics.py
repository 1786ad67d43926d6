"""The drift curve: path length and the start alignment (heading and origin only)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.pipeline.drift_metrics import drift_curve, path_length


def _line(n=200):
    t_ns = np.arange(n, dtype=np.int64) * 50_000_000
    p = np.stack([np.linspace(0, 40, n), 0.1 * np.sin(np.linspace(0, 3, n)), np.full(n, 1.5)],
                 axis=1)
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return GroundTruth(t_ns, p, q)


def test_path_length():
    np.testing.assert_allclose(path_length(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 2.0]])),
                               [0, 5, 7])


def test_heading_and_origin_are_aligned_away_and_drift_is_kept():
    gt = _line()
    turn = Rotation.from_euler("z", 0.7)
    est_p = turn.apply(gt.position) + [5.0, -2.0, 0.0]
    # a drift that starts after the alignment span: 0 for the first 10 m, then growing
    drift = np.where(gt.position[:, :1] > 12.0, 0.05 * (gt.position[:, :1] - 12.0), 0.0)
    est_p = est_p + turn.apply(np.hstack([np.zeros_like(drift), drift, np.zeros_like(drift)]))
    q = (turn * Rotation.from_quat(gt.quaternion[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    curve = drift_curve(GroundTruth(gt.t_ns, est_p, q), gt, align_m=10.0)
    np.testing.assert_allclose(curve["error_m"], drift[:, 0], atol=1e-9)
    assert curve["distance_m"][-1] > 40.0
    # without alignment the heading and origin count
    assert drift_curve(GroundTruth(gt.t_ns, est_p, q), gt, align_m=None)["error_m"][0] > 5.0
