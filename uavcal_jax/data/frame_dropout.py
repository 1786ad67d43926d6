"""A recording whose cameras go blind for a while: every frame of a time span black, or
blurred past use (a lens fogged, the sun in the lens, a dark tunnel), the IMU untouched.

Used to measure what carries an estimator through a visual dropout (issue 43: the VIO with and
without a learned prior on its biases). The frames are changed as they are loaded; nothing is
written.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from uavcal_jax.data.sequence import FrameStream, Sequence

__all__ = ["BLUR_SIGMA_PX", "DROPOUT_KINDS", "with_frame_dropout"]

#: What a dropped frame becomes.
DROPOUT_KINDS = ("black", "blur")
#: The blur's Gaussian standard deviation, pixels (at 752x480 no corner survives it).
BLUR_SIGMA_PX = 12.0


def _blind(stream: FrameStream, t0_ns: int, t1_ns: int, kind: str) -> FrameStream:
    inside = (stream.t_ns >= t0_ns) & (stream.t_ns < t1_ns)
    load = stream.loader

    def loader(i: int, color: str) -> np.ndarray:
        image = load(i, color)
        if not inside[i]:
            return image
        if kind == "black":
            return np.zeros_like(image)
        return cv2.GaussianBlur(image, (0, 0), BLUR_SIGMA_PX)

    return dataclasses.replace(stream, loader=loader)


def with_frame_dropout(sequence: Sequence, start_s: float, duration_s: float,
                       kind: str = "black") -> Sequence:
    """``sequence`` with every camera's frames in ``[t_first + start_s, ... + duration_s)``
    (``t_first`` the first left frame's time) made ``kind`` (:data:`DROPOUT_KINDS`). The
    result has no folder (``root`` ``None``), so that nothing cached for the recording as it
    was is read for it.

    Raises:
        ValueError: an unknown kind, or a negative start or duration.
    """
    if kind not in DROPOUT_KINDS:
        raise ValueError(f"kind must be one of {DROPOUT_KINDS}, got {kind!r}")
    if start_s < 0 or duration_s < 0:
        raise ValueError(f"start and duration must be >= 0 s, got {start_s}, {duration_s}")
    first = int(sequence.camera("cam0").t_ns[0])
    t0 = first + int(round(start_s * 1e9))
    t1 = t0 + int(round(duration_s * 1e9))
    cameras = {name: _blind(stream, t0, t1, kind) for name, stream in sequence.cameras.items()}
    # no folder: what an estimator caches beside a recording (its visual rotations, its VIO
    # poses) is of the frames as recorded, not of these
    return dataclasses.replace(sequence, cameras=cameras, root=None,
                               name=f"{sequence.name}+{kind}{duration_s:g}s")
