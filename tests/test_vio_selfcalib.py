"""The IMU-offset self-calibration of ``experiments/vio_selfcalib.py`` recovers an injected
EuRoC-sized offset on a tiny configuration (compared against the injected truth)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

from vio_selfcalib import (  # noqa: E402
    DEFAULT_ACCEL,
    DEFAULT_GYRO,
    SelfCalibConfig,
    recover_offset,
)


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
