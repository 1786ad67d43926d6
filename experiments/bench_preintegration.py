"""Benchmark IMU preintegration: one jitted, vmapped call over many windows vs GTSAM from Python.

The issue's set-up: 1,024 windows of 200 samples (1 s at 200 Hz) preintegrated in one jitted,
``jax.vmap``-ed call of :func:`uavcal_jax.imu.preintegrate` (means, bias Jacobians and the
9x9 covariance), against GTSAM 4.3's ``PreintegratedImuMeasurements.integrateMeasurement``
driven from Python over the same windows, in the same run. The windows are cut from the real
EuRoC V1_01 IMU stream (``../shared/data/euroc_v101_micro``) when it is there, otherwise from
a synthetic stream; the ground-truth biases / noise densities of the recording are used.

The batched call runs twice: on one CPU device (``jax.jit(jax.vmap(...))``) and split across
all host devices (``--devices``, default: one per CPU core) with
:func:`uavcal_jax.parallel.over_devices` -- XLA runs a scan of small steps on one core, so
the cores are used by giving each its share of the windows. GTSAM's loop is single-threaded
Python, as a user drives it.

Reported (seconds are wall-clock, medians of ``--repeats`` runs after a warm-up run;
throughput = windows x samples / seconds):

* ``compile_s``: tracing + XLA compilation of the batched call (once per configuration);
* ``ours_batch_s``, ``ours_samples_per_s``: the batched call on all devices, its inputs
  already split across them (:func:`uavcal_jax.parallel.shard_batch`), as the one-device
  call has its inputs on its device;
* ``ours_unplaced_batch_s``, ``ours_unplaced_samples_per_s``: the same with the inputs on the
  first device, so that each call also copies the other devices' shares;
* ``ours_1dev_batch_s``, ``ours_1dev_samples_per_s``: the same call on one device;
* ``gtsam_s``, ``gtsam_samples_per_s``: GTSAM's Python loop over the same windows;
* ``ratio`` (all devices) and ``ratio_1dev``: our throughput over GTSAM's;
* ``single_window_latency_s``: one window (jitted, compiled beforehand), median of many;
* ``float32_*``: the batched call (all devices) in float32 (``--no-float32`` to skip);
* the largest difference between our deltas and GTSAM's on the benchmark windows (a check
  that both sides did the same work).

The CPU is often shared; run it on a quiet machine for stable numbers. The last line printed
is one JSON object with at least ``ours_samples_per_s``, ``gtsam_samples_per_s`` and ``ratio``.

Usage::

    python experiments/bench_preintegration.py                 # 1024 x 200, float64
    python experiments/bench_preintegration.py --windows 256   # quicker
    python experiments/bench_preintegration.py --devices 1     # one device only
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np
from _bench import median, time_calls, time_compile  # the script's folder is first on sys.path
from _docs import add_write_docs, figures_table, write_docs

from uavcal_jax.argtypes import print_json
from uavcal_jax.data.euroc_rig import EUROC_IMU_RATE_HZ
from uavcal_jax.geometry.frames import GRAVITY, GRAVITY_W
from uavcal_jax.imu import EUROC_ADIS16448, interval_batch, preintegrate
from uavcal_jax.parallel import over_devices, shard_batch, use_cpu_devices

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "euroc_v101_micro"


def load_windows(n_windows: int, n_samples: int, seed: int = 0):
    """(dt, gyro, accel, bias_gyro, bias_accel, noise, source) for the benchmark windows."""
    if DATA.exists():
        from uavcal_jax.data.euroc import read_euroc

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            seq = read_euroc(DATA)
        imu, gt = seq.imu, seq.ground_truth
        n_total = len(imu) - n_samples - 1
        starts = np.linspace(0, n_total, n_windows).astype(int)
        batch = interval_batch(imu, starts=imu.t_ns[starts], ends=imu.t_ns[starts + n_samples])
        gidx = np.clip(np.searchsorted(gt.t_ns, imu.t_ns[starts]), 0, len(gt) - 1)
        noise = seq.imu_calibration.noise
        return (batch.dt, batch.gyro, batch.accel, gt.bias_gyro[gidx], gt.bias_accel[gidx],
                noise, "EuRoC V1_01 IMU (real)")
    rng = np.random.default_rng(seed)
    period = 1.0 / EUROC_IMU_RATE_HZ
    dt = np.full((n_windows, n_samples), period)
    t = np.arange(n_samples) * period
    phase = rng.uniform(0, 6, (n_windows, 1, 1))
    gyro = 0.5 * np.sin(2.0 * t[None, :, None] + phase) + rng.normal(0, 0.01, (n_windows,
                                                                               n_samples, 3))
    accel = -np.asarray(GRAVITY_W) + np.cos(1.3 * t[None, :, None] + phase)
    zeros = np.zeros((n_windows, 3))
    return dt, gyro, accel, zeros, zeros, EUROC_ADIS16448, "synthetic"


def gtsam_run(dt, gyro, accel, bg, ba, noise):
    """GTSAM's preintegration of every window from Python; returns (seconds, pims)."""
    import gtsam

    params = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    params.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise_density**2)
    params.setAccelerometerCovariance(np.eye(3) * noise.accel_noise_density**2)
    params.setIntegrationCovariance(np.zeros((3, 3)))
    pims = []
    t0 = time.perf_counter()
    for w in range(dt.shape[0]):
        pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias(ba[w], bg[w]))
        acc_w, gyr_w, dt_w = accel[w], gyro[w], dt[w]
        for k in range(dt.shape[1]):
            pim.integrateMeasurement(acc_w[k], gyr_w[k], dt_w[k])
        pims.append(pim)
    return time.perf_counter() - t0, pims


def time_ours(dt, gyro, accel, bg, ba, noise, repeats: int, scheme: str, devices):
    """(compile_s, median batch seconds, median batch seconds with the inputs on the first
    device, output) of the vmapped call on ``devices``.

    The inputs are first placed where the call reads them (:func:`shard_batch`: each device
    holds its share, as the one-device call holds all of it); the second figure also counts
    copying each share off the first device, as a call on freshly loaded data does."""
    batched = jax.vmap(lambda d, g, a, b1, b2: preintegrate(d, g, a, b1, b2, noise=noise,
                                                            scheme=scheme))
    fn = over_devices(batched, devices)
    host = [np.asarray(x) for x in (dt, gyro, accel, bg, ba)]
    args = shard_batch(host, devices)
    compiled, compile_s = time_compile(fn, *args)
    timed = time_calls(functools.partial(compiled, *args), repeats=repeats, warmup=1)
    batch_s, out = timed.median_s, timed.result
    if len(devices) == 1:  # nothing to copy
        return compile_s, batch_s, batch_s, out
    # what over_devices' call does, on the executable compiled above (no second compile)
    on_first = [jax.device_put(x, devices[0]) for x in host]
    unplaced_s = time_calls(lambda: compiled(*shard_batch(on_first, devices)),
                            repeats=repeats).median_s
    return compile_s, batch_s, unplaced_s, out


def single_window_latency(dt, gyro, accel, bg, ba, noise, scheme: str, n: int = 50) -> float:
    fn = jax.jit(lambda d, g, a, b1, b2: preintegrate(d, g, a, b1, b2, noise=noise,
                                                      scheme=scheme))
    args = [jax.device_put(x) for x in (dt[0], gyro[0], accel[0], bg[0], ba[0])]
    return time_calls(functools.partial(fn, *args), repeats=n, warmup=1).median_s


def max_difference(out, pims) -> dict:
    import gtsam

    d_rot = d_vel = d_pos = 0.0
    for w, pim in enumerate(pims):
        R = np.asarray(out.delta_R[w], float)
        d_rot = max(d_rot, float(np.abs(gtsam.Rot3.Logmap(gtsam.Rot3(pim.deltaRij().matrix().T
                                                                     @ R))).max()))
        d_vel = max(d_vel, float(np.abs(np.asarray(out.delta_v[w]) - pim.deltaVij()).max()))
        d_pos = max(d_pos, float(np.abs(np.asarray(out.delta_p[w]) - pim.deltaPij()).max()))
    return {"max_diff_rot_rad": d_rot, "max_diff_vel_mps": d_vel, "max_diff_pos_m": d_pos}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--windows", type=int, default=1024)
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--devices", type=int, default=os.cpu_count() or 1,
                   help="host CPU devices to split the windows over [default: one per core]")
    p.add_argument("--scheme", choices=("tangent", "manifold"), default="tangent")
    p.add_argument("--no-float32", action="store_true", help="skip the float32 run")
    p.add_argument("--no-gtsam", action="store_true", help="skip GTSAM (no ratio)")
    add_write_docs(p)
    args = p.parse_args(argv)
    n_devices = use_cpu_devices(args.devices)
    all_devices = jax.devices()[:args.devices]

    dt, gyro, accel, bg, ba, noise, source = load_windows(args.windows, args.samples)
    n_samples_total = args.windows * args.samples
    result: dict = {
        "windows": args.windows, "samples_per_window": args.samples, "data": source,
        "scheme": args.scheme, "platform": platform.platform(), "cpu_count": os.cpu_count(),
        "jax": jax.__version__, "backend": jax.default_backend(), "devices": len(all_devices),
    }
    if n_devices < args.devices:
        print(f"only {n_devices} device(s) available", file=sys.stderr)

    with jax.enable_x64(True):
        _, batch1_s, _, _ = time_ours(dt, gyro, accel, bg, ba, noise, args.repeats,
                                      args.scheme, all_devices[:1])
        compile_s, batch_s, unplaced_s, out64 = time_ours(dt, gyro, accel, bg, ba, noise,
                                                          args.repeats, args.scheme, all_devices)
        result["dtype"] = "float64"
        result["compile_s"] = compile_s
        result["ours_batch_s"] = batch_s
        result["ours_samples_per_s"] = n_samples_total / batch_s
        result["ours_unplaced_batch_s"] = unplaced_s
        result["ours_unplaced_samples_per_s"] = n_samples_total / unplaced_s
        result["ours_1dev_batch_s"] = batch1_s
        result["ours_1dev_samples_per_s"] = n_samples_total / batch1_s
        result["single_window_latency_s"] = single_window_latency(dt, gyro, accel, bg, ba,
                                                                  noise, args.scheme)
        out64 = jax.tree_util.tree_map(np.asarray, out64)
    result["all_valid"] = bool(np.all(out64.valid))
    print(f"ours  (float64): {batch_s * 1e3:8.1f} ms for {n_samples_total} samples on "
          f"{len(all_devices)} device(s) ({result['ours_samples_per_s'] / 1e6:.2f} M samples/s; "
          f"{unplaced_s * 1e3:.1f} ms with the inputs on one device), "
          f"{batch1_s * 1e3:.1f} ms on one device; compile {compile_s:.1f} s, "
          f"single window {result['single_window_latency_s'] * 1e3:.2f} ms", file=sys.stderr)

    if not args.no_float32:
        with jax.enable_x64(False):
            inputs32 = (np.asarray(x, np.float32) for x in (dt, gyro, accel, bg, ba))
            c32, b32, _, _ = time_ours(*inputs32, noise, args.repeats, args.scheme, all_devices)
        result["float32_compile_s"] = c32
        result["float32_batch_s"] = b32
        result["float32_samples_per_s"] = n_samples_total / b32
        print(f"ours  (float32): {b32 * 1e3:8.1f} ms "
              f"({result['float32_samples_per_s'] / 1e6:.2f} M samples/s)", file=sys.stderr)

    if not args.no_gtsam:
        times = []
        for _ in range(3):
            t, pims = gtsam_run(dt, gyro, accel, bg, ba, noise)
            times.append(t)
        gtsam_s = median(times)
        result["gtsam_s"] = gtsam_s
        result["gtsam_samples_per_s"] = n_samples_total / gtsam_s
        result["ratio"] = result["ours_samples_per_s"] / result["gtsam_samples_per_s"]
        result["ratio_1dev"] = result["ours_1dev_samples_per_s"] / result["gtsam_samples_per_s"]
        result["ratio_unplaced"] = (result["ours_unplaced_samples_per_s"]
                                    / result["gtsam_samples_per_s"])
        if "float32_samples_per_s" in result:
            result["ratio_float32"] = result["float32_samples_per_s"] / result[
                "gtsam_samples_per_s"]
        result.update(max_difference(out64, pims))
        print(f"gtsam (Python) : {gtsam_s * 1e3:8.1f} ms "
              f"({result['gtsam_samples_per_s'] / 1e6:.2f} M samples/s); ratio "
              f"{result['ratio']:.1f}x ({result['ratio_1dev']:.1f}x on one device)",
              file=sys.stderr)
    write_docs(args, "bench_preintegration", figures_table(result), argv=argv,
               anchor="GTSAM's PreintegratedImuMeasurements driven from Python, same run")
    print_json(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
