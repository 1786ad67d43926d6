"""The small calibrator weights shipped in the package (``uavcal demo``, and ``calib
predict`` without ``--checkpoint``).

They are a run folder like any ``calib train`` output, cut down to ``config.json`` and the
best checkpoint, under ``uavcal_jax/calib/weights/``. ``experiments/calib_default_weights.py``
makes them (``--preset shipped``): simulated procedural flights at the demo's resolution, 2 s
windows, the physical protocol and its ``total`` label (what a user subtracts), a small
model with the motion tokens of the front end's visual rotations and its gyro head starting
at their least-squares estimate. Train one on recordings of your own platform for its
accelerometer (``uavcal calib train``): the simulator's accelerometer is not a real one.

What they are worth, measured (``python experiments/calib_default_weights.py --install``: 24
flights of 20 s, 703 training and 185 held-out windows, best epoch 21 of 27, 20 min on 2
cores shared with other work): per 2 s held-out window, gx gy gz 0.0035 0.0052 0.0015 rad/s,
ax ay az 0.04 0.01 0.02 m/s^2, against 0.10 pooled for the mean offset (the weights before
the uncertainty head: the same to 0.001). Their predicted sigma (``model.variance``) is a
window's: on those held-out windows the z-scores' RMS is 0.9-1.6 per channel (1.22 pooled:
a little overconfident). Over whole unseen flights (``experiments/calib_blind.py``: three 30 s
flights along EuRoC trajectories, the median of the windows) the gyro is within 0.0005 rad/s
RMS and the accelerometer 0.10 m/s^2 (no correction: 0.055 and 0.21); the window's sigma
overstates the median's gyro error (z RMS 0.18) and understates the accelerometer's, a bias
the procedural training flights do not show (z RMS 2.2). On the real V1_01 IMU the gyro is
within 0.001 rad/s of the sensor's bias, the accelerometer up to 0.12 m/s^2 off (a sim-to-real
gap). The VIO's own bias states (``calib predict``'s default method) do better on the
accelerometer.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.errors import DataError

__all__ = ["DEFAULT_WEIGHTS", "default_weights"]

#: The shipped run folder.
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "demo"


def default_weights() -> Path:
    """:data:`DEFAULT_WEIGHTS`, checked to hold a run's ``config.json`` and checkpoints."""
    if not (DEFAULT_WEIGHTS / "config.json").is_file() or not (
            DEFAULT_WEIGHTS / "checkpoints" / "best").is_dir():
        raise DataError("the shipped calibrator weights are missing from this installation "
                        "(reinstall the package, or give --checkpoint RUN)", DEFAULT_WEIGHTS)
    return DEFAULT_WEIGHTS
