"""Does the IMU cover a camera's frames? (:func:`check_imu_covers`, before any work starts.)

Every consumer of a recording's IMU between frames (the VIO, the offset estimators)
integrates the samples around each frame; a frame with none is not an estimate but a reset,
and an IMU file cut short made ``uavcal run`` reset the VIO 40 times over a minute before it
found no bias estimate. So a frame is *covered* when the IMU has a sample at or before it and
one at or after it, less than :data:`MAX_IMU_GAP_S` apart; the frames that are not are named
in one line, by index and time.
"""

from __future__ import annotations

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError

__all__ = ["MAX_IMU_GAP_S", "check_imu_covers", "uncovered_frames"]

#: The longest stretch without an IMU sample (seconds) across which a frame is still
#: covered: five frame periods at EuRoC's 20 Hz, 50 periods of its 200 Hz IMU (the readers
#: warn about gaps of three IMU periods, :data:`uavcal_jax.data.timing.IMU_GAP_FACTOR`).
MAX_IMU_GAP_S = 0.25


def uncovered_frames(frame_t_ns: np.ndarray, imu_t_ns: np.ndarray,
                     max_gap_s: float = MAX_IMU_GAP_S) -> np.ndarray:
    """``(K,)`` int indices of the frames the IMU does not cover (module docstring).

    Args:
        frame_t_ns: ``(N,)`` int ns, the frames' times (increasing).
        imu_t_ns: ``(M,)`` int ns, the IMU's sample times (increasing; may be empty).
        max_gap_s: the longest gap between the samples around a covered frame, seconds.
    """
    t = np.asarray(frame_t_ns, np.int64)
    imu = np.asarray(imu_t_ns, np.int64)
    if imu.size == 0:
        return np.arange(t.size)
    after = np.searchsorted(imu, t, side="left")  # first sample at or after each frame
    before = np.searchsorted(imu, t, side="right") - 1  # last sample at or before it
    has_both = (before >= 0) & (after < imu.size)
    gap = np.where(has_both, imu[np.minimum(after, imu.size - 1)] - imu[np.maximum(before, 0)],
                   np.iinfo(np.int64).max)
    return np.flatnonzero(gap > int(round(max_gap_s * 1e9)))


def _spans(indices: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive runs of ``indices`` as ``(first, last)``."""
    if indices.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(indices) > 1)
    starts = np.concatenate([[indices[0]], indices[breaks + 1]])
    ends = np.concatenate([indices[breaks], [indices[-1]]])
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def check_imu_covers(sequence: Sequence, camera: str = "cam0", *,
                     max_frames: int | None = None) -> None:
    """Refuse ``sequence`` when its IMU does not cover every frame of ``camera`` (the first
    ``max_frames`` of them, when given), in one line naming the frames (indices and times,
    seconds since the first frame) and the IMU's span.

    Raises:
        DataError: no IMU, or frames without IMU.
    """
    where = sequence.root if sequence.root is not None else sequence.name
    if sequence.imu is None or len(sequence.imu) == 0:
        raise DataError("the recording has no IMU samples", where)
    t = np.asarray(sequence.camera(camera).t_ns, np.int64)[:max_frames]
    bad = uncovered_frames(t, sequence.imu.t_ns)
    if bad.size == 0:
        return
    spans = _spans(bad)
    t0 = t[0]

    def span(a: int, b: int) -> str:
        frames = f"frame {a}" if a == b else f"frames {a}-{b}"
        return f"{frames} ({(t[a] - t0) * 1e-9:.2f}-{(t[b] - t0) * 1e-9:.2f} s)"

    shown = ", ".join(span(a, b) for a, b in spans[:5]) + (
        f" and {len(spans) - 5} more spans" if len(spans) > 5 else "")
    imu = np.asarray(sequence.imu.t_ns, np.int64)
    raise DataError(f"the IMU does not cover {bad.size} of the {t.size} {camera} frames: "
                    f"{shown} have no IMU sample within {MAX_IMU_GAP_S:g} s on both sides "
                    f"(the IMU spans {(imu[0] - t0) * 1e-9:.2f}-{(imu[-1] - t0) * 1e-9:.2f} s, "
                    f"{len(imu)} samples; times since the first frame)", where)
