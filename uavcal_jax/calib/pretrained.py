"""The small calibrator weights shipped in the package (``uavcal demo``, and ``calib
predict`` without ``--checkpoint``).

They are a run folder like any ``calib train`` output, cut down to ``config.json`` and the
best checkpoint, under ``uavcal_jax/calib/weights/``. ``experiments/calib_default_weights.py``
makes them (its docstring holds the command, the data and the figures it reached): simulated
procedural flights at the demo's resolution, 2 s windows, the physical protocol, a small
model. They are a demonstration of the pipeline, not a calibrator for a real drone: train one
on recordings of your own platform (``uavcal calib train``).

What they are worth, measured (``python experiments/calib_default_weights.py --flights 32
--duration 20 --epochs 60 --install``: the ``small`` preset with 2 s windows at 20 Hz and the
physical protocol, 962 training and 222 held-out windows, early-stopped at epoch 19, best
epoch 13, 35 min on 2 shared cores): on the 6 held-out flights, 8 physical-range offsets each,
per-channel RMSE gx gy gz 0.039 0.037 0.034 rad/s, ax ay az 0.083 0.063 0.055 m/s^2, pooled
0.054, against 0.076 pooled (about 0.046 per gyro and 0.092 per accel channel) for the mean
offset, here no correction at all, and 0.133 for each window's mean IMU sample minus the
training mean. So they remove about a quarter of an offset of the size of real biases from
2 s of flight, no more: the simulated IMU's own turn-on bias (0.03 rad/s, 0.1 m/s^2 per axis)
sits on top of the injected offset and is not part of the label. The demo prints these
estimates beside the least-squares estimate that uses the ground truth.
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
