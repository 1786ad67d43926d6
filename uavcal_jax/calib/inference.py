"""Inference over a sequence reusing frame tokens across overlapping windows.

A 10 s window with a 1 s stride shares 9 s of frames with its neighbour, and the frame
encoder (the costly, per-patch part of the video reducer block) reads one frame at a time.
So instead of encoding ``n_windows * T`` frames, :func:`encode_frames` encodes each of the
sequence's ``F`` frames once, and :func:`predict_windows` gathers every window's tokens by
its ``frame_index`` row and runs the rest of the model. In deterministic mode the result
equals the full model on the gathered windows (padded slots, ``frame_index == -1``, are
masked out of every attention, so their token is irrelevant).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.calib.model import Calibrator

__all__ = ["encode_frames", "predict_windows"]


@functools.partial(jax.jit, static_argnames=("model",))
def _encode(model: Calibrator, variables, frames):
    return model.apply(variables, frames, method=Calibrator.encode_frames)


@functools.partial(jax.jit, static_argnames=("model",))
def _predict(model: Calibrator, variables, tokens, frame_index, frame_mask, imu, motion):
    gathered = None if tokens is None else tokens[jnp.maximum(frame_index, 0)]
    return model.apply(variables, gathered, imu, frame_mask, motion,
                       method=Calibrator.predict_from_frame_tokens)


def encode_frames(model: Calibrator, variables, frames, chunk: int = 64) -> jax.Array:
    """Tokens ``(F, d)`` of a sequence's frames ``(F, h, w)`` / ``(F, 3, h, w)`` (the model's
    layout), encoded ``chunk`` at a time (the last chunk zero-padded, so one compile)."""
    frames = np.asarray(frames)
    n = frames.shape[0]
    out = []
    for start in range(0, n, chunk):
        part = frames[start:start + chunk]
        if part.shape[0] < chunk and n > chunk:
            pad = np.zeros((chunk - part.shape[0],) + part.shape[1:], part.dtype)
            part = np.concatenate([part, pad])
        out.append(_encode(model, variables, part))
    return jnp.concatenate(out)[:n]


def predict_windows(model: Calibrator, variables, frame_tokens, frame_index, frame_mask,
                    imu, motion=None) -> jax.Array:
    """Offsets ``(W, C)`` of windows given by ``frame_index (W, T)`` into ``frame_tokens
    (F, d)`` (``None`` for the IMU-only model), ``frame_mask (W, T)``, the windows' IMU
    samples ``(W, T, C)`` and, for a model with ``motion_tokens``, their motion inputs
    (:meth:`uavcal_jax.data.windows.WindowSet.motion`, the gyro as recorded)."""
    return _predict(model, variables, frame_tokens, jnp.asarray(frame_index),
                    jnp.asarray(frame_mask, bool), jnp.asarray(imu, jnp.float32), motion)
