"""Windows: counts, nearest-IMU pairing, shared frame storage, padding, real data."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from uavcal_jax.data import read_euroc
from uavcal_jax.data.sequence import CameraCalibration, FrameStream, ImuData, Sequence
from uavcal_jax.data.windows import WindowConfig, make_windows, nearest_index
from uavcal_jax.errors import DataError, DataRepairWarning

T0 = 1_400_000_000_000_000_000
H0, W0 = 48, 64


def make_sequence(seconds: float = 30.0, rate: float = 20.0, drop=(), seed: int = 0,
                  color: bool = False) -> tuple[Sequence, dict]:
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate))
    keep = np.setdiff1d(np.arange(n), np.asarray(drop, dtype=np.int64))
    t_cam = T0 + keep * int(round(1e9 / rate))
    images = rng.integers(0, 256, size=(keep.size, H0, W0, 3), dtype=np.uint8)
    calls = {"n": 0}

    def loader(i: int, c: str) -> np.ndarray:
        calls["n"] += 1
        img = images[i]
        return img.copy() if c == "rgb" else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)

    cal = CameraCalibration(np.array([50.0, 50, 32, 24]), np.zeros(4), (W0, H0), rate, np.eye(4))
    cam = FrameStream("cam0", t_cam.astype(np.int64), (), cal, loader)
    n_imu = int(seconds * 200) + 10
    # IMU clock offset by 1.3 ms from the camera plus jitter: pairing is not trivial.
    t_imu = T0 - 20_000_000 + np.arange(n_imu) * 5_000_000 + 1_300_000 \
        + rng.integers(-400_000, 400_000, n_imu)
    imu = ImuData(t_imu.astype(np.int64), rng.normal(size=(n_imu, 3)),
                  rng.normal(size=(n_imu, 3)))
    seq = Sequence("synthetic", None, {"cam0": cam}, imu, None, None)
    return seq, {"images": images, "calls": calls, "t_cam": t_cam}


@pytest.mark.parametrize(("seconds", "duration", "stride", "expected"), [
    (30.0, 10.0, 1.0, 21),    # 600 frames, last at 29.95 s: starts 0..20
    (30.0, 5.0, 0.5, 51),
    (10.0, 10.0, 1.0, 1),     # exactly one window of 200 frames
    (12.5, 10.0, 1.0, 3),
])
def test_window_counts(seconds, duration, stride, expected):
    seq, _ = make_sequence(seconds)
    ws = make_windows(seq, WindowConfig(duration=duration, stride=stride, size=(32, 24)))
    assert len(ws) == expected
    assert ws.frames_per_window == int(round(duration * 20))
    assert ws.frame_mask.all()
    assert ws.frame_index.dtype == np.int32 and ws.frame_index.shape == (expected,
                                                                         ws.frames_per_window)
    np.testing.assert_array_equal(np.diff(ws.start_ns), int(stride * 1e9))
    # every frame within its window's time span
    t = ws.frame_t_ns[ws.frame_index]
    assert np.all(t >= ws.start_ns[:, None])
    assert np.all(t < ws.start_ns[:, None] + int(duration * 1e9))


def test_too_short_is_error():
    seq, _ = make_sequence(5.0)
    with pytest.raises(DataError, match="too short"):
        make_windows(seq, WindowConfig(size=(32, 24)))


def test_nearest_imu_brute_force():
    seq, _ = make_sequence(30.0, seed=3)
    ws = make_windows(seq, WindowConfig(size=(32, 24)))
    dt = np.abs(ws.frame_t_ns[:, None] - seq.imu.t_ns[None, :])
    np.testing.assert_array_equal(ws.imu_index, np.argmin(dt, axis=1))
    w = ws.window(7)
    i7 = ws.imu_index[ws.frame_index[7]]
    np.testing.assert_array_equal(w["gyro"], seq.imu.gyro[i7])
    np.testing.assert_array_equal(w["accel"], seq.imu.accel[i7])
    np.testing.assert_array_equal(w["imu_t_ns"], seq.imu.t_ns[i7])
    # the IMU range covers the window
    a, b = ws.imu_range[7]
    assert seq.imu.t_ns[a] >= ws.start_ns[7] and seq.imu.t_ns[a - 1] < ws.start_ns[7]
    assert seq.imu.t_ns[b - 1] < ws.start_ns[7] + 10 * 10**9


def test_nearest_index_ties_and_edges():
    ref = np.array([0, 10, 20], np.int64)
    np.testing.assert_array_equal(nearest_index(np.array([-5, 0, 4, 5, 6, 15, 25, 99]), ref),
                                  [0, 0, 0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(nearest_index(np.array([3, 7]), np.array([5])), [0, 0])
    rng = np.random.default_rng(0)
    ref = np.sort(rng.integers(0, 10**6, 500))
    ref = np.unique(ref)
    q = rng.integers(-10, 10**6 + 10, 2000)
    np.testing.assert_array_equal(nearest_index(q, ref),
                                  np.argmin(np.abs(q[:, None] - ref[None, :]), axis=1))


def test_frames_shared_not_copied():
    seq, info = make_sequence(60.0)
    ws = make_windows(seq, WindowConfig(duration=10.0, stride=1.0, size=(32, 24)))
    assert len(ws) == 51
    # Each frame decoded and stored exactly once, although ~10 windows use each one.
    assert ws.frames.shape == (1200, 24, 32)
    assert info["calls"]["n"] == 1200
    assert ws.frames.nbytes == 1200 * 24 * 32
    assert np.bincount(ws.frame_index.ravel()).max() == 10
    w0, w1 = ws.window(0)["frames"], ws.window(1)["frames"]
    assert w0.shape == (200, 24, 32)
    assert np.shares_memory(w0, ws.frames) and np.shares_memory(w1, ws.frames)
    assert np.shares_memory(w0, w1)  # overlapping windows are views of the same frames
    b = ws.batch([0, 1, 5])
    assert b["frames"].shape == (3, 200, 24, 32) and b["frames"].dtype == np.uint8
    assert not np.shares_memory(b["frames"], ws.frames)
    np.testing.assert_array_equal(b["frames"][1], w1)
    assert b["gyro"].shape == (3, 200, 3) and b["mask"].all()


def test_frame_step_keeps_every_kth_slot_and_decodes_only_those():
    seq, info = make_sequence(30.0, drop=[41])
    full = make_windows(seq, WindowConfig(size=(32, 24)))
    info["calls"]["n"] = 0
    ws = make_windows(seq, WindowConfig(size=(32, 24), frame_step=3))
    assert ws.frames_per_window == 67 and len(ws) == len(full)  # ceil(200 / 3)
    # the same frames (by time) in the kept slots, the dropped one still padded
    t_full = np.where(full.frame_mask, full.frame_t_ns[np.maximum(full.frame_index, 0)], -1)
    t_step = np.where(ws.frame_mask, ws.frame_t_ns[np.maximum(ws.frame_index, 0)], -1)
    np.testing.assert_array_equal(t_step, t_full[:, ::3])
    assert (t_step == -1).sum() == (t_full[:, ::3] == -1).sum() > 0
    assert info["calls"]["n"] == ws.frames.shape[0] == np.unique(ws.frame_index[ws.frame_mask]).size
    b, bf = ws.batch([2]), full.batch([2])
    np.testing.assert_array_equal(b["gyro"], bf["gyro"][:, ::3])
    with pytest.raises(ValueError, match="frame_step"):
        WindowConfig(frame_step=0)


def test_resize_is_inter_area_once():
    seq, info = make_sequence(10.0)
    ws = make_windows(seq, WindowConfig(size=(32, 24), color="rgb"))
    assert ws.frames.shape == (200, 24, 32, 3)
    ref = cv2.resize(info["images"][17], (32, 24), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(ws.frames[17], ref)
    gray = make_windows(seq, WindowConfig(size=(32, 24)))
    ref = cv2.resize(cv2.cvtColor(info["images"][5], cv2.COLOR_RGB2GRAY), (32, 24),
                     interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(gray.frames[5], ref)


def test_dropped_frames_padded_and_masked():
    drop = [105, 106, 107, 250]
    seq, info = make_sequence(15.0, drop=drop)
    ws = make_windows(seq, WindowConfig(size=(32, 24)))
    assert len(ws) == 6
    m0 = ws.frame_mask[0]
    assert m0.sum() == 197
    np.testing.assert_array_equal(np.flatnonzero(~m0), [105, 106, 107])
    assert np.all(ws.frame_index[0, ~m0] == -1)
    w = ws.window(0)
    assert w["frames"].shape == (200, 24, 32)
    assert not np.shares_memory(w["frames"], ws.frames)
    assert np.all(w["frames"][105:108] == 0) and np.all(w["t_ns"][105:108] == -1)
    assert np.all(w["gyro"][105:108] == 0)
    # frames after the gap keep their time slot
    np.testing.assert_array_equal(w["t_ns"][108:] - ws.start_ns[0],
                                  np.arange(108, 200) * 50_000_000)
    # window k starts k s later (frame 20 k): the same frames sit in other slots
    assert np.flatnonzero(~ws.frame_mask[1]).tolist() == [85, 86, 87]
    assert np.flatnonzero(~ws.frame_mask[5]).tolist() == [5, 6, 7, 150]
    b = ws.batch([0])
    np.testing.assert_array_equal(b["frames"][0], w["frames"])


def test_min_valid_fraction_skips_sparse_windows():
    seq, _ = make_sequence(12.0, drop=list(range(20, 220)))  # windows keep 20, 0, 20 of 200
    with pytest.raises(DataError, match="at least"):
        make_windows(seq, WindowConfig(size=(32, 24)))
    ws = make_windows(seq, WindowConfig(size=(32, 24), min_valid_fraction=0.1))
    assert len(ws) == 2 and ws.frame_mask.sum(axis=1).tolist() == [20, 20]
    np.testing.assert_array_equal(ws.start_ns - ws.start_ns[0], [0, 2 * 10**9])


@pytest.mark.realdata
def test_real_micro_windows(euroc_micro):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataRepairWarning)
        seq = read_euroc(euroc_micro)
    with pytest.raises(DataError, match="too short"):
        make_windows(seq, WindowConfig())  # 4.7 s of frames < 10 s
    ws = make_windows(seq, WindowConfig(duration=2.0, stride=0.5))
    assert len(ws) == 6 and ws.frames_per_window == 40
    # windows start at 0, 0.5, ..., 2.5 s: frames up to 4.45 s are used, loaded once
    assert ws.frames.shape == (90, 180, 320) and ws.frame_mask.all()
    ref = cv2.resize(seq.cameras["cam0"].load(10), (320, 180), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(ws.frames[10], ref)
    dt = np.abs(ws.frame_t_ns[:, None] - seq.imu.t_ns[None, :])
    np.testing.assert_array_equal(ws.imu_index, np.argmin(dt, axis=1))
    assert dt.min(axis=1).max() <= 2_500_000  # 200 Hz IMU: within half a period
    # the sensor's own bias over each window, from the ground truth's b_w / b_a columns
    gt = seq.ground_truth
    inside = (gt.t_ns >= ws.start_ns[2]) & (gt.t_ns < ws.start_ns[2] + 2_000_000_000)
    want = np.concatenate([gt.bias_gyro[inside], gt.bias_accel[inside]], axis=1).mean(axis=0)
    np.testing.assert_allclose(ws.sensor_bias[2], want, rtol=1e-12)
    # V1_01's real gyro bias, steady over the slice
    np.testing.assert_allclose(ws.sensor_bias[:, :3], [[-0.0022, 0.0215, 0.0770]] * 6, atol=5e-4)
    np.testing.assert_array_equal(ws.batch([1, 4])["sensor_bias"], ws.sensor_bias[[1, 4]])


def test_no_bias_columns_no_sensor_bias():
    seq, _ = make_sequence(12.0)
    ws = make_windows(seq, WindowConfig(duration=10.0, stride=1.0, size=(32, 24)))
    assert ws.sensor_bias is None and "sensor_bias" not in ws.batch([0])


def test_subset_picks_windows_and_shares_frames():
    seq, _ = make_sequence(30.0)
    ws = make_windows(seq, WindowConfig(duration=10.0, stride=5.0, size=(32, 24)))
    sub = ws.subset([3, 0])
    assert len(sub) == 2 and sub.frames is ws.frames and sub.gyro is ws.gyro
    np.testing.assert_array_equal(sub.start_ns, ws.start_ns[[3, 0]])
    np.testing.assert_array_equal(sub.imu_range, ws.imu_range[[3, 0]])
    for k in ("frames", "mask", "gyro", "imu_t_ns"):
        np.testing.assert_array_equal(sub.window(0)[k], ws.window(3)[k])
        np.testing.assert_array_equal(sub.window(1)[k], ws.window(0)[k])
