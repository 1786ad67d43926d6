"""The small calibrator weights shipped in the package (``uavcal demo``, and ``calib
predict`` without ``--checkpoint``).

They are a run folder like any ``calib train`` output, cut down to ``config.json`` and the
best checkpoint, under ``uavcal_jax/calib/weights/``. ``experiments/calib_default_weights.py``
makes them (``--preset shipped``): simulated procedural flights at the demo's resolution, each
with a real multirotor's airframe (rotor drag, a tilted thrust axis, the IMU's mounting tilt),
2 s windows, the physical protocol and its ``total`` label (what a user subtracts), a small
model with the motion tokens of the front end's visual rotations and its head starting at the
metric closed form (``rotation_alignment``): the gyro's least squares against the camera's
rotations, the accelerometer's visual-inertial alignment of the stereo VIO's poses over the
20 s around each window (so predicting runs the VIO once per recording, its poses kept beside
it), with the alignment's standard deviation as an input. Train one on recordings of your own
platform for its accelerometer (``uavcal calib train``).

What they are (issue 43): the run's learned correction is **switched off** (the head's
weights zeroed, ``--closed-form-only``). Trained, it lowered the held-out procedural windows'
error, but on unseen flights along real EuRoC trajectories (11 flights of 20 s from 40 s in,
seed 11: ``experiments/calib_uncertainty.py``) it made both sensors worse: gyro 0.0009
against 0.0006 rad/s, accelerometer 0.036 against 0.020 m/s^2 RMS per axis (0.12-0.13 off on
two flights where the closed form was 0.04). What is learned and kept is the uncertainty
head: each window's sigma, scaled by the measured ``common_scale`` of ``uncertainty.json``
(the share the windows of one recording have in common: 0.16 gyro, 1.52 accelerometer).
The weights before (the gyro closed form, the accelerometer learned from the IMU and frames
alone) were 0.0006 rad/s and 0.093 m/s^2 off on the same flights. Made by::

    python experiments/calib_default_weights.py --closed-form-only uavcal_jax/calib/weights/demo
    python experiments/calib_uncertainty.py --methods transformer --write-run
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
