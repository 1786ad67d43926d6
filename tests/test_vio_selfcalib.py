"""The IMU-offset self-calibration (:mod:`uavcal_jax.vio.selfcalib`) recovers an injected
EuRoC-sized offset on a tiny configuration (compared against the injected truth)."""

from __future__ import annotations

import numpy as np
import pytest

from uavcal_jax.vio.selfcalib import (
    DEFAULT_ACCEL,
    DEFAULT_GYRO,
    SelfCalibConfig,
    offset_errors,
    recover_offset,
)


@pytest.mark.heavy
def test_recover_offset_removes_most_of_the_error():
    offset = np.array(DEFAULT_GYRO + DEFAULT_ACCEL)
    cfg = SelfCalibConfig(windows=2, n_frames=8, n_landmarks=50, keyframe_dt=0.2, steps=4)
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
        SelfCalibConfig(method="adam")
