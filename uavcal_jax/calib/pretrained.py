"""The small calibrator weights shipped in the package (``uavcal demo``, and ``calib
predict`` without ``--checkpoint``).

They are a run folder like any ``calib train`` output, cut down to ``config.json`` and the
best checkpoint, under ``uavcal_jax/calib/weights/``. ``experiments/calib_default_weights.py``
makes them (its docstring holds the command, the data and the figures it reached): simulated
procedural flights at the demo's resolution, 2 s windows, the physical protocol, a small
model. They are a demonstration of the pipeline, not a calibrator for a real drone: train one
on recordings of your own platform (``uavcal calib train``).

What they are worth, measured (``python experiments/calib_default_weights.py --flights 32
--duration 20 --epochs 60``: 962 training and 222 held-out windows, early-stopped at epoch 11,
best epoch 7, 14 min on 2 cores): on the 6 held-out flights with 24 physical-range offsets,
per-channel RMSE gx gy gz 0.059 0.062 0.048 rad/s, ax ay az 0.091 0.101 0.106 m/s^2, against
0.052 0.055 0.051 and 0.093 0.091 0.096 for no correction at all. So this budget does **not**
learn offsets of the size of real biases: the gyro offset shows only as a drift of a few
pixels over a 2 s window against the integrated gyro, which a d-64 transformer does not pick
out of raw patches in minutes of CPU training. The demo prints these estimates beside the
least-squares estimate that uses the ground truth.
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
