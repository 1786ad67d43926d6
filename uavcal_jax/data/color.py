"""Colour conventions shared by every producer and consumer of frames."""

from __future__ import annotations

__all__ = ["LUMA_WEIGHTS"]

#: ITU-R BT.601 luma weights of R, G, B: the grayscale image of an RGB frame, as OpenCV's
#: ``COLOR_RGB2GRAY`` computes it (the renderer's gray frames, the calibrator's eq. 1).
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
