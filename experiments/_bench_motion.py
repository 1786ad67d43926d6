"""The cost of the calibrator's motion tokens (issue 20), for ``bench_calibrator.py``.

- :func:`bench_front_end`: the VIO front end's frame-to-frame camera rotations
  (:func:`uavcal_jax.vio.visual_rotation.timed_relative_rotations`, what
  ``window.rotations=visual`` computes once per recording) on the real V1_01 slice, per
  752x480 frame, and scaled to a 60 s sequence at 20 Hz.
- :func:`bench_motion_model`: a preset's model with ``model.motion_tokens`` and the
  ``rotation_ls`` closed form against the same model without them, timed in turn (one call
  of each, ``repeats`` rounds after two of warm-up; the windows, then the sequences): one
  window, and the
  windows of a 60 s sequence from frame tokens (:func:`uavcal_jax.calib.inference.
  predict_windows`, the frames encoded once, the encoding's cost is the same either way).

Inputs are synthetic, with the shapes :meth:`uavcal_jax.data.windows.WindowSet.motion`
gives: ``S`` IMU samples per frame interval (200 Hz IMU, 20 Hz frames: 10, padded to
:data:`INTERVAL_CAP`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np
from _bench import median, time_calls, time_compile
from scipy.spatial.transform import Rotation

from uavcal_jax.calib import inference
from uavcal_jax.calib.config import CalibConfig
from uavcal_jax.calib.train import create_train_state
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.euroc_rig import EUROC_IMU_RATE_HZ, EUROC_RATE_HZ
from uavcal_jax.vio.visual_rotation import timed_relative_rotations

#: Samples per frame interval in the synthetic motion inputs (10 real, then padding).
INTERVAL_CAP = 12


def synthetic_motion(rng: np.random.Generator, lead: tuple[int, ...]) -> dict:
    """Motion inputs ``lead + (T, ...)`` (``lead`` ends with ``T``): gyro ``(..., S, 3)``
    rad/s, ``dt (..., S)`` s (10 samples of 5 ms, then padding), small camera rotations, the
    first slot of each window invalid."""
    per = int(round(EUROC_IMU_RATE_HZ / EUROC_RATE_HZ))
    dt = np.zeros(lead + (INTERVAL_CAP,), np.float32)
    dt[..., :per] = 1.0 / EUROC_IMU_RATE_HZ
    rot = Rotation.from_rotvec(rng.normal(0.0, 0.02, (int(np.prod(lead)), 3)))
    mask = np.ones(lead, bool)
    mask[..., 0] = False
    return {"gyro_seq": rng.normal(0.0, 0.3, lead + (INTERVAL_CAP, 3)).astype(np.float32),
            "dt_seq": dt, "rot_cam": rot.as_matrix().reshape(lead + (3, 3)).astype(np.float32),
            "rot_mask": mask}


def bench_front_end(recording: Path, sequence_s: float) -> dict:
    """The front end's rotations per frame on ``recording`` and over ``sequence_s`` seconds at
    20 Hz; ``{"skipped": why}`` when the recording is absent."""
    if not recording.is_dir():
        return {"skipped": f"{recording} not found"}
    seq = read_euroc(recording)
    timed_relative_rotations(seq)  # warm-up: OpenCV's first calls, the page cache
    rotations, per_frame_s = timed_relative_rotations(seq)
    frames = int(round(sequence_s * EUROC_RATE_HZ))
    return {"recording": recording.name, "frames": len(seq.camera("cam0")),
            "pairs": int(rotations.t0_ns.size), "ms_per_frame": round(1e3 * per_frame_s, 2),
            "sequence_s": sequence_s, "sequence_frames": frames,
            "sequence_cost_s": round(per_frame_s * frames, 2)}


def bench_motion_model(config: CalibConfig, window: dict, tokens_index, sequence_imu,
                       rng: np.random.Generator, repeats: int) -> dict:
    """One window and a sequence's windows, with and without motion tokens (module
    docstring). ``window``: a batch of one window (frames, imu, mask); ``tokens_index``:
    ``(frame_tokens_count, frame_index (W, T))``; ``sequence_imu (W, T, 6)``."""
    motion_config = dataclasses.replace(config, model=dataclasses.replace(
        config.model, motion_tokens=True, closed_form="rotation_ls"))
    T = window["imu"].shape[1]
    n_tokens, index = tokens_index
    seq_motion = synthetic_motion(rng, index.shape)
    calls, out = {}, {}
    for name, cfg, extra in (("plain", config, {}),
                             ("motion", motion_config, synthetic_motion(rng, (1, T)))):
        state = create_train_state(cfg, jax.random.key(0), {**window, **extra})
        model, variables = state.model, state.variables()
        motion = extra or None
        apply = jax.jit(lambda v, f, i, m, mo, model=model: model.apply(v, f, i, m, mo))
        args = (variables, window["frames"], window["imu"], window["mask"], motion)
        compiled, compile_s = time_compile(apply, *args)
        tokens = np.asarray(rng.normal(size=(n_tokens, cfg.model.d_model)), np.float32)
        mask = np.ones(index.shape, bool)
        seq_args = (model, variables, tokens, index, mask, sequence_imu,
                    seq_motion if extra else None)
        jax.block_until_ready(inference.predict_windows(*seq_args))  # compiles
        calls[name] = (lambda c=compiled, a=args: c(*a),
                       lambda a=seq_args: inference.predict_windows(*a))
        out[name] = {"window_compile_s": round(compile_s, 2)}
    # interleaved, one call of each model in turn (this machine's speed drifts by a quarter);
    # the windows first, then the sequences: a sequence's large temporaries between two
    # window calls would make each window fault its memory in anew
    for kind, (key, scale, digits) in enumerate((("window_ms", 1e3, 2),
                                                 ("sequence_predict_s", 1.0, 4))):
        walls: dict[str, list[float]] = {name: [] for name in calls}
        for r in range(repeats + 2):
            for name, pair in calls.items():
                wall = time_calls(pair[kind], repeats=1, warmup=1 if r == 0 else 0).wall_s
                if r >= 2:  # two rounds of warm-up
                    walls[name].extend(wall)
        for name, wall in walls.items():
            out[name][key] = round(scale * median(wall), digits)
    out["window_extra_ms"] = round(out["motion"]["window_ms"] - out["plain"]["window_ms"], 2)
    out["sequence_extra_s"] = round(out["motion"]["sequence_predict_s"]
                                    - out["plain"]["sequence_predict_s"], 4)
    return out
