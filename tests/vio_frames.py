"""Test helpers: the stereo VIO frame by frame over a sequence, with chosen frames blacked out,
and the ATE of the estimates it returns."""

from __future__ import annotations

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.vio import ate
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.frame_estimate import FrameEstimate
from uavcal_jax.vio.run import VioResult, stereo_pairs


def process_frames(seq: Sequence, black: range = range(0)
                   ) -> tuple[list[FrameEstimate], StereoVio]:
    """:meth:`StereoVio.process` on every stereo pair of ``seq``; the pairs whose index is in
    ``black`` get all-black images. Returns the estimates and the estimator."""
    cam0, cam1 = seq.camera("cam0"), seq.camera("cam1")
    vio = StereoVio(cam0.calibration, cam1.calibration, seq.imu_calibration, seq.imu)
    out = []
    for k, (t_ns, i, j) in enumerate(stereo_pairs(seq)):
        left = cam0.load(i)
        right = cam1.load(j) if j is not None else None
        if k in black:
            left, right = np.zeros_like(left), np.zeros_like(left)
        out.append(vio.process(t_ns, left, right))
    return out, vio


def frames_ate(frames: list[FrameEstimate], seq: Sequence):
    """Translation ATE statistics of ``frames`` against ``seq``'s ground truth."""
    trajectory = VioResult(frames, 0, 0, None, np.zeros(6)).trajectory()
    return ate(trajectory, seq.ground_truth).translation
