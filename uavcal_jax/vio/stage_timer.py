"""Per-frame stage timings of the estimator's back end, recorded in one place
(:attr:`~uavcal_jax.vio.frame_estimate.FrameEstimate.timings`)."""

from __future__ import annotations

import time

__all__ = ["TIMING_KEYS", "StageTimer"]

#: Keys of ``FrameEstimate.timings``, in order: the stages of one frame, then ``total``.
TIMING_KEYS = ("frontend", "solve", "marginalize", "total")


class StageTimer:
    """Milliseconds of one frame's stages. Started when the back end takes the frame; the
    front end's time is handed over, the others end at :meth:`lap`.

    Args:
        frontend_ms: what the front end took (another thread may have run it).
    """

    def __init__(self, frontend_ms: float):
        self._start = self._mark = time.perf_counter()
        self._ms = {"frontend": frontend_ms}

    def lap(self, stage: str) -> None:
        """``stage`` (``solve`` or ``marginalize``) ends now; it began at the previous lap (or
        at the start)."""
        now = time.perf_counter()
        self._ms[stage] = 1e3 * (now - self._mark)
        self._mark = now

    def timings(self) -> dict[str, float]:
        """:data:`TIMING_KEYS` -> ms: a stage that did not run is 0, ``total`` the front end's
        time plus the back end's so far."""
        out = {stage: self._ms.get(stage, 0.0) for stage in TIMING_KEYS[:-1]}
        out["total"] = out["frontend"] + 1e3 * (time.perf_counter() - self._start)
        return out
