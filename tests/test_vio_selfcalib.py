"""The IMU-offset self-calibration (:mod:`uavcal_jax.vio.selfcalib`) recovers an injected
EuRoC-sized offset on a tiny configuration (compared against the injected truth)."""

from __future__ import annotations

import numpy as np
import pytest

from uavcal_jax.vio.selfcalib import (
    DEFAULT_ACCEL,
    DEFAULT_GYRO,
    DescentConfig,
    SelfCalibConfig,
    offset_errors,
    pin_window_biases,
    recover_offset,
)


@pytest.mark.heavy
def test_recover_offset_removes_most_of_the_error():
    offset = np.array(DEFAULT_GYRO + DEFAULT_ACCEL)
    cfg = SelfCalibConfig(windows=2, n_frames=8, n_landmarks=50, keyframe_dt=0.2,
                          descent=DescentConfig(steps=4))
    res = recover_offset(offset, cfg)
    np.testing.assert_array_equal(res["err_before"], np.abs(offset))
    np.testing.assert_allclose(res["err_after"], np.abs(res["estimate"] - offset))
    assert res["loss"][-1] < res["loss"][0]
    # at least 80 % of the error removed in every channel
    assert np.all(res["removed"] >= 0.8), res["removed"]
    assert res["removed_scaled"] >= 0.8


def test_offset_errors_and_config_checks():
    injected = np.array([0.02, 0.0, -0.01, 0.1, -0.2, 0.0])
    e = offset_errors(injected, 0.5 * injected)
    np.testing.assert_allclose(e["removed"][[0, 2, 3, 4]], 0.5)
    assert np.isnan(e["removed"][[1, 5]]).all(), "nothing injected: no fraction"
    assert e["removed_gyro"] == pytest.approx(0.5) and e["removed_scaled"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="newton"):
        DescentConfig(method="adam")


def test_pinning_the_biases_keeps_the_priors_pose_information_and_pins_the_biases():
    """:func:`pin_window_biases` on a window whose prior informs every state of its first
    three keyframes (the fourth is unused): the new prior's information on the poses and
    velocities is the Schur complement of the old one's bias block, its biases are pinned at
    zero with the given sigmas on every keyframe in use and on none other, nothing couples
    the two, and the start has zero biases."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from uavcal_jax.vio.synthetic import SyntheticConfig, synthetic_window
    from uavcal_jax.vio.window import FRAME_DIM, Prior

    with jax.enable_x64(True):
        w = synthetic_window(SyntheticConfig(n_frames=4, n_landmarks=8), seed=1)
        n = 4
        used = np.array([True, True, True, False])
        rng = np.random.default_rng(0)
        dim = FRAME_DIM * n
        J = np.zeros((dim, dim))
        J[:, :FRAME_DIM * 3] = rng.normal(size=(dim, FRAME_DIM * 3))
        r = rng.normal(size=dim)
        lin = dataclasses.replace(w.truth.frames,
                                  bias_gyro=jnp.asarray(rng.normal(0.0, 0.02, (n, 3))),
                                  bias_accel=jnp.asarray(rng.normal(0.0, 0.1, (n, 3))))
        problem = dataclasses.replace(
            w.problem, frame_mask=jnp.asarray(used),
            prior=Prior(jnp.asarray(J), jnp.asarray(r), lin, jnp.asarray(True)))
        start, pinned = pin_window_biases(w.truth, problem, sigma_gyro=1e-3, sigma_accel=1e-2)
        J_new, r_new = np.asarray(pinned.prior.J), np.asarray(pinned.prior.r)
        H_new, b_new = J_new.T @ J_new, J_new.T @ r_new
        H, b = J.T @ J, J.T @ r
        index = np.arange(dim).reshape(n, FRAME_DIM)
        bias, rest = index[:3, 9:].ravel(), index[:3, :9].ravel()
        schur = H[np.ix_(rest, rest)] - H[np.ix_(rest, bias)] @ np.linalg.solve(
            H[np.ix_(bias, bias)], H[np.ix_(bias, rest)])
        np.testing.assert_allclose(H_new[np.ix_(rest, rest)], schur, rtol=1e-6, atol=1e-6)
        b_schur = b[rest] - H[np.ix_(rest, bias)] @ np.linalg.solve(H[np.ix_(bias, bias)],
                                                                     b[bias])
        np.testing.assert_allclose(b_new[rest], b_schur, rtol=1e-6, atol=1e-6)
        weight = np.tile(np.r_[np.full(3, 1e6), np.full(3, 1e4)], 3)
        np.testing.assert_allclose(H_new[np.ix_(bias, bias)], np.diag(weight), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(H_new[np.ix_(rest, bias)], 0.0, atol=1e-6)
        # the pin is on the bias itself: 0.5 w (b_lin + d)^2 about the prior's linearisation
        lin_bias = np.concatenate([np.asarray(lin.bias_gyro), np.asarray(lin.bias_accel)],
                                  axis=1)[:3]
        np.testing.assert_allclose(b_new[bias], weight * lin_bias.ravel(), rtol=1e-6)
        np.testing.assert_allclose(H_new[index[3]][:, index[3]], 0.0, atol=1e-9)  # unused
        assert not np.any(np.asarray(start.frames.bias_gyro))
        assert not np.any(np.asarray(start.frames.bias_accel))
