"""Speed of the IMU-offset transformer (Avola et al., Sensors 2023): training step, inference.

Two presets: ``paper`` -- the :class:`~uavcal_jax.calib.config.CalibConfig` defaults (batch
16; d 256, 8 heads, 2 layers, 64x64 patches) on 200-frame windows of 320x180 uint8 grayscale
(10 s at 20 Hz, the :class:`~uavcal_jax.data.windows.WindowConfig` geometry) -- and ``small``
(batch 4, 50 frames, d 128; the peer's ``--small``). Inputs are synthetic, with the shapes
and dtypes :func:`uavcal_jax.calib.data.gather` produces (``frames (B, T, 180, 320)`` uint8,
``imu (B, T, 6)`` float32, ``mask (B, T)`` bool, ``weight (B,)``), placed on the device once
(host-to-device copies are the input pipeline's cost, not the step's). Per preset:

* ``params``: parameter count (the peer takes the first patch's output row as the frame
  token, so it lacks the learned frame token and one patch position: ``peer_params_minus_ours``
  shows the difference).
* ``train_step_s``: one :func:`~uavcal_jax.calib.train.train_step` (offset draw, injection,
  forward, backward, AdamW), compiled first (``train_compile_s``, timed apart), warm-up
  steps (2; 1 at paper size, the peer's too), then the median of the timed steps, each fed
  the state the last one returned; ``train_cpu_s`` is the process CPU time per step (all
  threads), a load-independent measure.
* ``window_ms``: the deterministic model (initial weights) on ONE 10 s window (batch 1),
  jitted and compiled apart (``window_compile_s``); the target is at most 100 ms
  (``window_meets_100ms``). Inference (window and sequence) is measured before the
  training step, in a process that has not trained, as ``uavcal calib predict`` runs.
  ``window_bf16_*``: the same with ``ModelConfig.frame_encoder_dtype="bfloat16"`` (the frame
  encoder's products on bfloat16 operands with float32 sums; same weights), and
  ``window_bf16_token_rel_rms``, its frame tokens' relative RMS difference from float32's.
* ``sequence``: a 60 s sequence, 10 s windows with a 1 s stride (51 windows), from host
  arrays to offsets: ``reuse_s`` encodes each frame once
  (:func:`~uavcal_jax.calib.inference.encode_frames`, chunks of 64) and runs the rest of the
  model on all windows at once (:func:`~uavcal_jax.calib.inference.predict_windows`), split
  into ``reuse_encode_s`` and ``reuse_predict_s``;
  ``full_s`` runs the whole model window by window (the compiled single-window function, each
  window's frames gathered from the sequence). ``speedup = full_s / reuse_s``;
  ``max_abs_diff`` compares their offsets (they must agree). The reuse path's first call
  (compiling its two functions) is ``reuse_first_call_s``.
* ``peer``: the PyTorch peer (``../shared/tools/peer_calibrator_torch.py --bench``) run as a
  subprocess with the same preset and thread count after ours (never beside it), its JSON
  line, and ``peer_step_over_ours`` / ``peer_window_over_ours`` (above 1: ours is faster).
  ``null`` with ``peer_error`` when the interpreter is missing or the run fails.

``motion`` (issue 20's motion tokens, :mod:`_bench_motion`): per preset, ``motion_model``
gives the one-window time and the 60 s sequence's window predictions (from frame tokens)
with ``model.motion_tokens`` and the ``rotation_ls`` closed form beside the same model
without them (``window_extra_ms``, ``sequence_extra_s``); once, ``motion_front_end`` gives
the front end's frame-to-frame rotations per 752x480 frame on the real V1_01 slice and their
cost over a 60 s sequence (computed once per recording and cached; ``--no-motion`` skips
both).

``seeds`` (small preset, run after both presets):
:func:`~uavcal_jax.calib.train.train_step_seeds` on K = 8 stacked states against the small
preset's :func:`~uavcal_jax.calib.train.train_step` on one; ``per_seed_ratio`` is
``(time(K=8) / 8) / time(K=1)`` (below 1: vmapping seeds shares work).

Memory: ``peak_rss_mib_after`` is the process peak RSS (``resource.getrusage``) when a stage
is done -- a running maximum: small runs first and the seeds last, so the small preset's
figure is its own and the paper's is its own unless below the small one's;
``*_xla_temp_mib`` is XLA's planned temporary buffers of the compiled function
(``Compiled.memory_analysis``); ``device_memory`` is ``Device.memory_stats()`` where the
backend has them (``None`` on XLA:CPU). The peer's ``peak_rss_mib`` is its ``VmHWM`` polled
from ``/proc`` (its own getrusage figure inherits ours across fork/exec: see
:func:`run_peer`).

Allocator: the benchmark runs under :func:`uavcal_jax.allocator.keep_freed_memory`, as the
``uavcal`` command does (``allocator_keeps_freed_memory``; ``UAVCAL_KEEP_FREED_MEMORY=0``
turns it off). ``peer`` is the peer as its README runs it (glibc's default allocator);
``peer_same_allocator`` runs it again under our setting, with its own ``*_over_ours`` ratios:
PyTorch on CPU mallocs and frees its large tensors every step as well, and gains from it too.

Threads: XLA:CPU sizes its thread pool by the CPUs this process may run on (its affinity),
not by a setting; the peer gets ``torch.set_num_threads(--threads)``, by default that same
count. To compare on fewer cores, run the whole benchmark under ``taskset -c 0-1`` (the
peer inherits the affinity). The 1-minute load average before and after is recorded: on a
shared CPU the wall-clock figures include other processes' time.

The last line printed is one JSON object.

Usage::

    python experiments/bench_calibrator.py                      # both presets and the peer
    python experiments/bench_calibrator.py --small-only --repeats 2 --no-peer
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _bench import (  # the script's folder is first on sys.path
    median,
    time_calls,
    time_compile,
    time_once,
)
from _bench_motion import bench_front_end, bench_motion_model
from _docs import (  # the script's folder is first on sys.path
    add_write_docs,
    figures_table,
    write_docs,
)

from uavcal_jax import allocator
from uavcal_jax.argtypes import positive_int, print_json
from uavcal_jax.calib import inference
from uavcal_jax.calib.config import CalibConfig
from uavcal_jax.calib.model import Calibrator
from uavcal_jax.calib.train import (
    create_train_state,
    create_train_states,
    train_step,
    train_step_seeds,
)
from uavcal_jax.config import apply_overrides
from uavcal_jax.data.windows import WindowConfig
from uavcal_jax.geometry.frames import GRAVITY_W

REPO = Path(__file__).resolve().parents[1]
DEFAULT_PEER_PYTHON = REPO.parent / "peer-venv" / "bin" / "python"
DEFAULT_PEER_SCRIPT = REPO.parent / "shared" / "tools" / "peer_calibrator_torch.py"
#: The real stereo slice the front end's rotations are timed on.
MICRO = REPO.parent / "shared" / "data" / "euroc_v101_micro"

# (batch, frames per 10 s window, d_model); heads, layers and patch stay the defaults.
PRESETS = {"small": (4, 50, 128), "paper": (16, 200, 256)}
SEQUENCE_S = 60.0  # the sequence of the reuse comparison, seconds
SEEDS_K = 8
WINDOW_TARGET_MS = 100.0
PEER_TIMEOUT_S = 3600.0
MIB = 2.0 ** 20
#: ``python -c PEER_PRELUDE allocator.py script args...``: apply the allocator setting, then
#: run the peer script as ``__main__`` with its own arguments.
PEER_PRELUDE = ("import runpy, sys; runpy.run_path(sys.argv[1])['keep_freed_memory'](); "
                "sys.argv = sys.argv[2:]; runpy.run_path(sys.argv[0], run_name='__main__')")


def preset_config(batch: int, d_model: int) -> CalibConfig:
    """The default configuration with the preset's batch size and width."""
    return apply_overrides(CalibConfig(), {"train.batch_size": batch, "model.d_model": d_model})


def synthetic_imu(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """IMU samples ``shape + (6,)`` float32: gyro rad/s about 0, accel m/s^2 about gravity."""
    gyro = rng.normal(0.0, 0.3, shape + (3,))
    accel = rng.normal(0.0, 0.5, shape + (3,)) - np.asarray(GRAVITY_W)
    return np.concatenate([gyro, accel], axis=-1).astype(np.float32)


def synthetic_batch(rng: np.random.Generator, batch: int, frames: int,
                    hw: tuple[int, int]) -> dict:
    """A training batch as :func:`uavcal_jax.calib.data.gather` returns it (every slot real)."""
    return {"frames": rng.integers(0, 256, (batch, frames) + hw, dtype=np.uint8),
            "imu": synthetic_imu(rng, (batch, frames)),
            "mask": np.ones((batch, frames), bool),
            "weight": np.ones(batch, np.float32)}


def sequence_windows(n_frames: int, per_window: int, stride: int) -> np.ndarray:
    """``frame_index (W, T)`` of every window of ``per_window`` frames, ``stride`` apart."""
    starts = np.arange(0, n_frames - per_window + 1, stride)
    return (starts[:, None] + np.arange(per_window)[None, :]).astype(np.int32)


def _rounded(values, digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]


def _xla_temp_mib(compiled) -> float | None:
    try:
        stats = compiled.memory_analysis()
    except Exception:  # not every backend / jax version implements it
        return None
    return None if stats is None else round(stats.temp_size_in_bytes / MIB, 1)


def _device_memory() -> dict | None:
    stats = jax.devices()[0].memory_stats()
    if not stats:
        return None
    names = {"bytes_in_use": "in_use_mib", "peak_bytes_in_use": "peak_in_use_mib",
             "bytes_limit": "limit_mib"}
    return {v: round(stats[k] / MIB, 1) for k, v in names.items() if k in stats}


def _peak_rss_mib() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)  # KiB on Linux


def _param_count(params) -> int:
    return int(sum(np.size(x) for x in jax.tree.leaves(params)))


def _progress(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def bench_training(config: CalibConfig, batch: dict, repeats: int, warmup: int) -> dict:
    """Compile and time :func:`train_step` on ``batch``; returns the figures."""
    state = create_train_state(config, jax.random.key(0), batch)
    dev_batch = jax.device_put(batch)
    keys = jax.random.split(jax.random.key(1), repeats + warmup)
    step, compile_s = time_compile(train_step, state, dev_batch, keys[0])
    holder = {"state": state, "i": 0}
    losses = []

    def one():
        s, metrics = step(holder["state"], dev_batch, keys[holder["i"]])
        jax.block_until_ready(s)
        holder["state"], holder["i"] = s, holder["i"] + 1
        losses.append(float(metrics["loss"]))

    timed = time_calls(one, repeats=repeats, warmup=warmup)
    wall, cpu = timed.wall_s, timed.cpu_s
    if not np.all(np.isfinite(losses)):
        raise RuntimeError(f"non-finite training loss: {losses}")
    return {"params": _param_count(state.params), "train_compile_s": round(compile_s, 2),
            "train_step_s": round(median(wall), 4), "train_step_s_runs": _rounded(wall),
            "train_cpu_s": round(median(cpu), 4), "train_xla_temp_mib": _xla_temp_mib(step),
            "train_loss_first_last": _rounded([losses[0], losses[-1]])}


def bench_window(model: Calibrator, variables, window: dict, repeats: int,
                 name: str = "window") -> tuple[dict, object]:
    """Compile and time the deterministic model on one window; returns the figures (keys
    starting with ``name``) and the compiled function ``(variables, frames, imu, mask) ->
    offsets``."""
    apply = jax.jit(lambda v, f, i, m: model.apply(v, f, i, m))
    args = (variables, jax.device_put(window["frames"]), jax.device_put(window["imu"]),
            jax.device_put(window["mask"]))
    compiled, compile_s = time_compile(apply, *args)
    timed = time_calls(lambda: compiled(*args), repeats=repeats, warmup=2)
    wall, cpu = timed.wall_s, timed.cpu_s
    ms = 1e3 * median(wall)
    return {f"{name}_compile_s": round(compile_s, 2), f"{name}_ms": round(ms, 2),
            f"{name}_ms_min": round(1e3 * min(wall), 2),
            f"{name}_ms_runs": _rounded([1e3 * t for t in wall], 1),
            f"{name}_cpu_ms": round(1e3 * median(cpu), 2),
            f"{name}_meets_100ms": bool(ms <= WINDOW_TARGET_MS),
            f"{name}_xla_temp_mib": _xla_temp_mib(compiled)}, compiled


def bench_window_bf16(model: Calibrator, variables, window: dict, repeats: int) -> dict:
    """:func:`bench_window` with ``frame_encoder_dtype="bfloat16"`` (same variables), and
    ``window_bf16_token_rel_rms``: the RMS of its frame tokens' difference from float32's over
    the float32 tokens' RMS, on this window's frames."""
    half = Calibrator(dataclasses.replace(model.config, frame_encoder_dtype="bfloat16"))
    out, _ = bench_window(half, variables, window, repeats, name="window_bf16")
    ref, got = (np.asarray(inference.encode_frames(m, variables, window["frames"][0]))
                for m in (model, half))
    out["window_bf16_token_rel_rms"] = float(np.sqrt(np.mean((got - ref) ** 2)
                                                     / np.mean(ref ** 2)))
    return out


def bench_sequence(model: Calibrator, variables, window_fn, rng: np.random.Generator,
                   per_window: int, hw: tuple[int, int], repeats: int) -> dict:
    """A 60 s sequence with and without frame-token reuse (see the module docstring)."""
    wc = WindowConfig()
    rate = per_window / wc.duration  # frames (and IMU samples) per second
    n_frames = int(round(SEQUENCE_S * rate))
    index = sequence_windows(n_frames, per_window, int(round(wc.stride * rate)))
    frames = rng.integers(0, 256, (n_frames,) + hw, dtype=np.uint8)
    imu = synthetic_imu(rng, (n_frames,))[index]  # (W, T, 6): each window's samples
    mask = np.ones(index.shape, bool)

    split: list[tuple[float, float]] = []  # (encode, predict) seconds of each reuse call

    def reuse():
        t0 = time.perf_counter()
        tokens = jax.block_until_ready(inference.encode_frames(model, variables, frames))
        t1 = time.perf_counter()
        out = jax.block_until_ready(
            inference.predict_windows(model, variables, tokens, index, mask, imu))
        split.append((t1 - t0, time.perf_counter() - t1))
        return out

    def full():
        out = [window_fn(variables, frames[index[w]][None], imu[w][None], mask[w][None])
               for w in range(index.shape[0])]
        return jax.block_until_ready(jnp.concatenate(out))

    # the first call compiles the frame encoder (one chunk shape) and the window predictor
    reused, first_s = time_once(reuse)
    reuse_wall = time_calls(reuse, repeats=repeats).wall_s
    diff = float(np.max(np.abs(np.asarray(reused) - np.asarray(full()))))  # also the warm-up
    full_wall = time_calls(full, repeats=repeats).wall_s
    reuse_s, full_s = median(reuse_wall), median(full_wall)
    return {"seconds": SEQUENCE_S, "frames": n_frames, "windows": int(index.shape[0]),
            "reuse_first_call_s": round(first_s, 2), "reuse_s": round(reuse_s, 4),
            "reuse_s_runs": _rounded(reuse_wall),
            "reuse_encode_s": round(median([e for e, _ in split[1:]]), 4),
            "reuse_predict_s": round(median([q for _, q in split[1:]]), 4),
            "full_s": round(full_s, 4),
            "full_s_runs": _rounded(full_wall), "speedup": round(full_s / reuse_s, 2),
            "max_abs_diff": diff}


def bench_seeds(config: CalibConfig, batch: dict, k: int, repeats: int, warmup: int,
                one_seed_s: float) -> dict:
    """``train_step_seeds`` on ``k`` stacked seeds against ``one_seed_s`` (``train_step``)."""
    states = create_train_states(config, jax.random.split(jax.random.key(2), k), batch)
    dev_batch = jax.device_put(batch)
    keys = jax.random.split(jax.random.key(3), (repeats + warmup) * k).reshape(-1, k)
    step, compile_s = time_compile(train_step_seeds, states, dev_batch, keys[0])
    holder = {"states": states, "i": 0}

    def one():
        s, _ = step(holder["states"], dev_batch, keys[holder["i"]])
        holder["states"], holder["i"] = jax.block_until_ready(s), holder["i"] + 1

    wall = time_calls(one, repeats=repeats, warmup=warmup).wall_s
    step_s = median(wall)
    return {"k": k, "compile_s": round(compile_s, 2), "step_s": round(step_s, 4),
            "step_s_runs": _rounded(wall), "per_seed_s": round(step_s / k, 4),
            "one_seed_s": round(one_seed_s, 4),
            "per_seed_ratio": round(step_s / k / one_seed_s, 3),
            "xla_temp_mib": _xla_temp_mib(step)}


def _vm_hwm_mib(pid: int) -> float | None:
    """``VmHWM`` (peak resident set) of process ``pid`` from ``/proc``, MiB; None if gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return None


def run_peer(python: Path, script: Path, preset: str, threads: int, warmup: int,
             train_steps: int, infer_runs: int, keep_freed: bool
             ) -> tuple[dict | None, str | None]:
    """The peer's JSON line for ``preset``, or ``(None, reason)``.

    ``keep_freed``: start the peer under the allocator setting the ``uavcal`` command runs
    with (:func:`uavcal_jax.allocator.keep_freed_memory`, read from its file by
    :data:`PEER_PRELUDE`: the peer's interpreter has no uavcal_jax), so both sides pay the
    same page faults; ``False``: as its README runs it.

    The peer's own ``peak_rss_mib`` (getrusage) is wrong when it is started from this
    process: Linux carries the parent's high-water mark across fork/exec, so it reports at
    least ours. Its ``VmHWM`` (per address space, reset by exec) is polled from ``/proc``
    while it runs and replaces it; the peer's figure is kept as ``peak_rss_mib_getrusage``.
    """
    if not Path(python).exists():
        return None, f"peer interpreter {python} not found"
    if not Path(script).exists():
        return None, f"peer script {script} not found"
    prelude = ["-c", PEER_PRELUDE, allocator.__file__] if keep_freed else []
    cmd = [str(python), *prelude, str(script), "--bench", "--threads", str(threads),
           "--warmup-steps", str(warmup), "--train-steps", str(train_steps),
           "--warmup-infer", "2", "--infer-runs", str(infer_runs)]
    if preset == "small":
        cmd.append("--small")
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    except OSError as exc:
        return None, f"peer did not start: {exc}"
    hwm, t0 = None, time.monotonic()
    while True:
        try:
            stdout, stderr = proc.communicate(timeout=0.25)
            break
        except subprocess.TimeoutExpired:
            now = _vm_hwm_mib(proc.pid)
            hwm = now if hwm is None or (now or 0) > hwm else hwm
            if time.monotonic() - t0 > PEER_TIMEOUT_S:
                proc.kill()
                proc.communicate()
                return None, f"peer ran past {PEER_TIMEOUT_S} s"
    lines = [ln for ln in stdout.splitlines() if ln.startswith("{")]
    if proc.returncode or not lines:
        tail = (stderr or stdout).strip().splitlines()[-3:] or ["no JSON line printed"]
        return None, f"peer exited {proc.returncode}: {' | '.join(tail)}"
    try:
        peer = json.loads(lines[-1])
    except json.JSONDecodeError as exc:
        return None, f"peer printed no valid JSON: {exc}"
    peer["peak_rss_mib_getrusage"] = peer.get("peak_rss_mib")
    peer["peak_rss_mib"] = None if hwm is None else round(hwm, 1)
    return peer, None


def bench_preset(name: str, args, rng: np.random.Generator, quiet: bool) -> dict:
    """Every per-preset figure of the module docstring for preset ``name``."""
    batch_size, per_window, d_model = PRESETS[name]
    heavy = name == "paper"
    repeats = min(args.repeats, args.heavy_repeats) if heavy else args.repeats
    warmup = 1 if heavy else 2  # training steps, ours and the peer's
    config = preset_config(batch_size, d_model)
    w, h = WindowConfig().size
    hw = (h, w)
    out: dict = {"config": {"batch": batch_size, "frames": per_window, "frame_hw": list(hw),
                            "d_model": d_model, "heads": config.model.heads,
                            "layers": config.model.layers, "patch": list(config.model.patch),
                            "frame_token": config.model.frame_token}}
    # inference first, in a process that has not trained yet, as `uavcal calib predict` runs
    _progress(quiet, f"[{name}] one window ...")
    window = synthetic_batch(rng, 1, per_window, hw)
    state = create_train_state(config, jax.random.key(0), window)
    model, variables = state.model, state.variables()
    win, window_fn = bench_window(model, variables, window, args.window_repeats)
    out.update(win)
    out.update(bench_window_bf16(model, variables, window, args.window_repeats))
    _progress(quiet, f"[{name}] 60 s sequence ...")
    out["sequence"] = bench_sequence(model, variables, window_fn, rng, per_window, hw,
                                     repeats)
    if not args.no_motion:
        _progress(quiet, f"[{name}] motion tokens ...")
        wc = WindowConfig()
        rate = per_window / wc.duration
        n_frames = int(round(SEQUENCE_S * rate))
        index = sequence_windows(n_frames, per_window, int(round(wc.stride * rate)))
        out["motion_model"] = bench_motion_model(
            config, window, (n_frames, index), synthetic_imu(rng, index.shape), rng,
            args.window_repeats)
    del state, window_fn
    batch = synthetic_batch(rng, batch_size, per_window, hw)
    _progress(quiet, f"[{name}] training step ...")
    out.update(bench_training(config, batch, repeats, warmup))
    del batch
    out["peak_rss_mib_after"] = _peak_rss_mib()
    out["device_memory"] = _device_memory()
    # the peer as its README runs it, then (when this process keeps freed memory) under the
    # same allocator setting as ours
    for key, same in (("peer", False), ("peer_same_allocator", True)):
        if args.no_peer:
            out[key], out[f"{key}_error"] = None, "skipped (--no-peer)"
        elif same and not args.keep_freed_memory:
            out[key], out[f"{key}_error"] = None, "this run keeps glibc's default allocator"
        else:
            _progress(quiet, f"[{name}] PyTorch peer{' (same allocator)' if same else ''} ...")
            out[key], out[f"{key}_error"] = run_peer(
                args.peer_python, args.peer_script, name, args.threads, warmup, repeats,
                args.repeats, keep_freed=same)
        peer = out[key]
        out[f"{key}_step_over_ours"] = (
            None if peer is None else round(peer["train_step_s_median"] / out["train_step_s"], 2))
        out[f"{key}_window_over_ours"] = (
            None if peer is None else round(1e3 * peer["infer_window_s_median"]
                                            / out["window_ms"], 2))
    out["peer_params_minus_ours"] = (None if out["peer"] is None
                                     else out["peer"]["params"] - out["params"])
    return out


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_table(presets: dict, seeds: dict) -> None:
    head = (f"{'preset':7}{'params':>11}{'step s':>9}{'compile s':>10}{'window ms':>10}"
            f"{'bf16 ms':>8}"
            f"{'60s reuse s':>12}{'60s full s':>11}{'speedup':>8}{'peer step':>10}"
            f"{'peer win':>9}{'RSS MiB':>9}")
    print(head)
    for name, r in presets.items():
        peer = r["peer"] or {}
        win = peer.get("infer_window_s_median")
        print(f"{name:7}{r['params']:>11,}{r['train_step_s']:>9.3f}{r['train_compile_s']:>10.1f}"
              f"{r['window_ms']:>10.1f}{r['window_bf16_ms']:>8.1f}"
              f"{r['sequence']['reuse_s']:>12.3f}"
              f"{r['sequence']['full_s']:>11.3f}{r['sequence']['speedup']:>8.1f}"
              f"{_fmt(peer.get('train_step_s_median'), '10.3f'):>10}"
              f"{_fmt(None if win is None else 1e3 * win, '9.1f'):>9}"
              f"{r['peak_rss_mib_after']:>9.0f}")
        if r["peer"] is None:
            print(f"  {name} peer: {r['peer_error']}")
        else:
            print(f"  {name}: peer/ours step {r['peer_step_over_ours']}x, "
                  f"window {r['peer_window_over_ours']}x (peer {peer['params']:,} params, "
                  f"peak RSS {peer['peak_rss_mib']:.0f} MiB)")
        same = r["peer_same_allocator"]
        if same is not None:
            print(f"  {name}, peer under our allocator setting: step "
                  f"{same['train_step_s_median']:.3f} s ({r['peer_same_allocator_step_over_ours']}x"
                  f"), window {1e3 * same['infer_window_s_median']:.1f} ms "
                  f"({r['peer_same_allocator_window_over_ours']}x)")
    s = seeds
    print(f"small, K={s['k']} vmapped seeds: {s['step_s']:.3f} s per step = "
          f"{s['per_seed_s']:.3f} s per seed vs {s['one_seed_s']:.3f} s for one seed: "
          f"ratio {s['per_seed_ratio']:.2f} (peak RSS {s['peak_rss_mib_after']:.0f} MiB after)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--small-only", action="store_true",
                    help="skip the paper preset (quick runs)")
    ap.add_argument("--repeats", type=positive_int, default=5,
                    help="timed runs per measurement, after warm-up [default: 5]")
    ap.add_argument("--window-repeats", type=positive_int, default=20,
                    help="timed runs of the one-window inference (float32 and bfloat16), "
                         "after 2 warm-up runs; cheap, and a shared CPU's wall times spread "
                         "wide [default: 20]")
    ap.add_argument("--heavy-repeats", type=positive_int, default=3,
                    help="at most this many timed runs of the paper preset's training step "
                         "and 60 s sequence, and of the peer's paper training step "
                         "[default: 3]")
    ap.add_argument("--threads", type=positive_int, default=len(os.sched_getaffinity(0)),
                    help="the peer's torch threads [default: the CPUs this process may use, "
                         "which is what sizes XLA's pool]")
    ap.add_argument("--peer-python", type=Path, default=DEFAULT_PEER_PYTHON,
                    help="interpreter with torch for the peer [default: ../peer-venv]")
    ap.add_argument("--peer-script", type=Path, default=DEFAULT_PEER_SCRIPT)
    ap.add_argument("--no-peer", action="store_true", help="do not run the PyTorch peer")
    ap.add_argument("--no-motion", action="store_true",
                    help="skip the motion tokens' cost (front end and model)")
    ap.add_argument("--json-only", action="store_true",
                    help="print only the JSON line (no progress, no table)")
    add_write_docs(ap)
    args = ap.parse_args(argv)
    args.keep_freed_memory = allocator.keep_freed_memory()  # as the uavcal command runs

    cpus = len(os.sched_getaffinity(0))
    summary: dict = {
        "device": str(jax.devices()[0]), "jax": jax.__version__,
        "cpu_count": os.cpu_count(), "schedulable_cpus": cpus, "threads": args.threads,
        "threads_note": ("XLA's pool uses the schedulable CPUs; the peer uses --threads"
                         + ("" if args.threads == cpus else " (they differ: use taskset)")),
        "machine": platform.machine(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "repeats": args.repeats, "heavy_repeats": args.heavy_repeats,
        "window_repeats": args.window_repeats,
        "memory_source": "peak RSS: resource.getrusage(RUSAGE_SELF).ru_maxrss (running max); "
                         "xla_temp: Compiled.memory_analysis(); device_memory: "
                         "Device.memory_stats() (None on XLA:CPU)",
        "window_target_ms": WINDOW_TARGET_MS,
        "allocator_keeps_freed_memory": args.keep_freed_memory,
    }
    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(0)
    names = ["small"] if args.small_only else ["small", "paper"]  # small first: see RSS
    presets = {name: bench_preset(name, args, rng, args.json_only) for name in names}
    _progress(args.json_only, f"[small] K={SEEDS_K} seeds ...")
    batch_size, per_window, d_model = PRESETS["small"]
    w, h = WindowConfig().size
    seeds = bench_seeds(preset_config(batch_size, d_model),
                        synthetic_batch(rng, batch_size, per_window, (h, w)), SEEDS_K,
                        args.repeats, 2, presets["small"]["train_step_s"])
    seeds["peak_rss_mib_after"] = _peak_rss_mib()
    if not args.no_motion:
        _progress(args.json_only, "front end's rotations on the real slice ...")
        summary["motion_front_end"] = bench_front_end(MICRO, SEQUENCE_S)
    main_name = names[-1]
    top = presets[main_name]
    summary.update({
        "preset": main_name, "params": top["params"], "train_step_s": top["train_step_s"],
        "window_ms": top["window_ms"], "window_meets_100ms": top["window_meets_100ms"],
        "window_bf16_ms": top["window_bf16_ms"],
        "window_bf16_meets_100ms": top["window_bf16_meets_100ms"],
        "sequence_speedup": top["sequence"]["speedup"],
        "peer_step_over_ours": top["peer_step_over_ours"],
        "peer_window_over_ours": top["peer_window_over_ours"],
        "peer_same_allocator_step_over_ours": top["peer_same_allocator_step_over_ours"],
        "peer_same_allocator_window_over_ours": top["peer_same_allocator_window_over_ours"],
        "seeds_per_seed_ratio": seeds["per_seed_ratio"],
        "motion_window_ms": top.get("motion_model", {}).get("motion", {}).get("window_ms"),
        "peak_rss_mib": _peak_rss_mib(),
        "load_avg_1min": [load_before, os.getloadavg()[0]],
        "presets": presets, "seeds": seeds,
    })
    if not args.json_only:
        print_table(presets, seeds)
    write_docs(args, "bench_calibrator", figures_table(summary, (
        "preset", "params", "train_step_s", "window_ms", "window_bf16_ms", "motion_window_ms",
        "sequence_speedup", "peer_step_over_ours", "peer_window_over_ours",
        "peer_same_allocator_step_over_ours", "seeds_per_seed_ratio", "peak_rss_mib")),
               argv=argv,
               anchor="the PyTorch peer in the same run (peer_*_over_ours: its time over ours)")
    print_json(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
