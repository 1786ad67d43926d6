"""The offset estimators of ``uavcal_jax.pipeline`` and ``uavcal calib predict --method``.

On a 4 s simulated V2_01 flight (376x240 frames at 10 Hz) carrying a recorded offset, with
another one injected by ``--inject``: ``vio-bias`` recovers the gyro part of the total constant
error (offsets plus the simulated IMU's own bias, from the ground truth) to 2e-3 rad/s; every
method's estimate is the same with the ground-truth folder and the simulator's record
removed; estimators are handed no ground truth and the injected IMU, and are scored under
their own label afterwards; ``visual-ls`` recovers the gyro part from the frames' rotations, and
``self-calib`` by descending through the VIO's own windows; bad methods,
arguments and keys are one line and exit 2. (The accelerometer alignment's accuracy is
tested in ``test_imu_accel_alignment.py``: 4 s is too short a flight for it.)
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import warnings

import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.cli import main
from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.offset_json import read_offset_json
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.data.true_offset import sensor_bias
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS, OffsetEstimate, OffsetMethod
from uavcal_jax.pipeline.offset_estimators import METHODS, configure_method
from uavcal_jax.pipeline.predict_offset import known_offset, predict_offset, score
from uavcal_jax.pipeline.vio_bias import VioBiasOptions, tail_median
from uavcal_jax.sim.config import IDEAL_IMU, SimConfig
from uavcal_jax.sim.simulate import simulate

#: The offset the simulator writes into the IMU (sim_config.json) and the one --inject adds.
RECORDED = (0.03, -0.045, 0.02, 0.12, -0.08, 0.1)
INJECT = (-0.02, 0.015, 0.01, 0.1, 0.0, -0.05)
#: Gyro error bound, rad/s (measured on this flight: about 3e-4 and 1e-3 at most per axis).
GYRO_TOLERANCE = 2e-3
DURATION_S = 4.0
#: ``self-calib``'s, rad/s (issue 20's bound): two windows of a 4 s flight at 10 Hz hold less
#: than the VIO's 27 tracked frames; measured 2.8e-3 at most per axis.
SELF_CALIB_GYRO_TOLERANCE = 5e-3


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    trajectory = shared_path("trajectories", "euroc", "V2_01_easy.txt")
    out = tmp_path_factory.mktemp("offsets") / "flight"
    # an IMU with its data sheet's noise only: V1_01's vibration moves a 4 s mean by 1e-3
    # rad/s, more than the bounds here (visual-ls 2.4e-3 off with it); the constant's recovery
    # is this file's subject, the realistic IMU's cost the tables' (calib_blind)
    simulate(SimConfig(trajectory=str(trajectory), start=5.0, duration=DURATION_S, seed=4,
                       resolution=(376, 240), camera_rate_hz=10.0, depth=False, targets=False,
                       imu_offset=RECORDED, **IDEAL_IMU), out, progress=False)
    return out


@pytest.fixture(scope="module")
def cli_run(flight, tmp_path_factory):
    """``calib predict --method vio-bias --inject ... --out ... --json`` on the flight: its
    summary and the offsets file."""
    out = tmp_path_factory.mktemp("cli") / "offsets.json"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["calib", "predict", "--sequence", str(flight), "--method", "vio-bias",
                     "--inject=" + ",".join(map(str, INJECT)), "--out", str(out), "--json"])
    assert code == 0
    return json.loads(stdout.getvalue()), out


#: Each method's options on this short flight. ``self-calib``: the last 40 %: on so short a
#: flight the window just after the VIO's start is not settled (measured 0.04 rad/s off at
#: 1.8 s, 0.004 at 2.6 s); the descent's default 4 steps (3 left the z gyro 0.0055 rad/s off
#: once the halls' textures changed: a step short of converged).
OPTIONS = {"self-calib": ["windows=2", "tail_fraction=0.4", "descent.steps=4"]}


def _predict(root, method, options=None, inject=INJECT):
    """``uavcal calib predict``'s path: the recording read once, the method's estimate, then
    scored by the caller that holds the truth."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence, _ = read_sequence(root)
    summary, estimate = predict_offset(sequence, method, options, inject=inject)
    recorded = recorded_imu_offset(root)
    summary.update(recorded=None if recorded is None else recorded.tolist(),
                   **score(estimate, known_offset(recorded, inject), sequence.ground_truth))
    return summary, estimate


@pytest.fixture(scope="module")
def self_calib_run(flight):
    return _predict(flight, "self-calib", configure_method("self-calib", OPTIONS["self-calib"]))


def _ground_truth(root):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_euroc(root).ground_truth


def test_vio_bias_recovers_the_injected_gyro_offset(flight, cli_run):
    res, out = cli_run
    for key in ("method", "label", "channels", "offset", "per_window", "per_window_std",
                "window_start_s", "span_ns", "injected", "recorded", "true", "error", "rmse",
                "items", "frames", "frames_used", "resets", "out", "config"):
        assert key in res, key
    assert res["method"] == "vio-bias" and res["label"] == "total"
    assert res["channels"] == list(SIX_CHANNELS)
    np.testing.assert_allclose(res["recorded"], RECORDED)
    np.testing.assert_allclose(res["injected"], INJECT)
    # the truth: both offsets plus the simulated IMU's own bias over the span used
    bias = sensor_bias(_ground_truth(flight), *res["span_ns"])
    true = np.add(RECORDED, INJECT) + bias
    np.testing.assert_allclose(res["true"], true, atol=1e-12)
    offset = np.asarray(res["offset"])
    assert np.all(np.abs(offset[:3] - true[:3]) < GYRO_TOLERANCE), offset[:3] - true[:3]
    np.testing.assert_allclose(res["error"], offset - true, atol=1e-12)
    # the gyro: the median of the tracked frames of the last two thirds of the flight; the
    # accelerometer: the batch alignment of the tracked trajectory
    per_frame = np.asarray(res["per_window"])
    assert per_frame.shape == (res["items"], 6) and res["items"] == res["frames_used"]
    assert res["frames_used"] >= 0.5 * res["frames"] and res["resets"] == 0
    np.testing.assert_allclose(offset[:3], np.median(per_frame[:, :3], axis=0))
    assert res["accel"] == "alignment" and res["alignment"]["nodes"] >= 6
    assert min(res["window_start_s"]) >= DURATION_S / 3 - 0.2
    # the offsets file feeds `uavcal vio --offsets`; the settings went beside it
    np.testing.assert_allclose(read_offset_json(out), offset)
    record = json.loads(out.with_suffix(".config.json").read_text())
    assert record["tail_fraction"] == pytest.approx(2 / 3)
    assert record["vio"]["cost"]["focal_px"] > 0  # resolved against the recording's camera
    assert record["command"]["method"] == "vio-bias"


# self-calib's descent through the VIO's windows compiles for 2 minutes: heavy, not CI
def _check_pooled_scores(method: str, summary: dict) -> None:
    """``pooled_scores`` of a method's summary as ``score_recordings`` rows it: a finite score
    per channel, and a z-score spread where the method predicts a sigma of one per channel."""
    from uavcal_jax.pipeline.offset_scores import pooled_scores

    sigma = summary.get("sigma")
    if sigma is not None:
        assert np.shape(sigma) == (len(summary["channels"]),), (method, np.shape(sigma))
    row = {"recording": "flight", "method": method, "channels": summary["channels"],
           "offset": summary["offset"], "true": summary["true"], "error": summary["error"],
           "sigma": sigma}
    pooled = pooled_scores([row, {**row, "recording": "again"}])[method]
    assert pooled["recordings"] == 2
    assert all(np.isfinite(v) for v in pooled["rmse"].values())
    for sensor in ("gyro", "accel"):
        if sigma is not None and pooled[f"{sensor}_rmse"] is not None:
            assert np.isfinite(pooled[f"{sensor}_z_rms"])


@pytest.mark.parametrize("method", [pytest.param(m, marks=pytest.mark.heavy)
                                    if m == "self-calib" else m for m in sorted(METHODS)])
def test_every_method_is_the_same_without_ground_truth(flight, cli_run, self_calib_run, tmp_path,
                                                       method):
    """Each method run on the recording, then on it with its ground-truth folder and the
    simulator's record deleted: the same estimate, to the bit (no truth reaches a method).
    The VIO methods' first runs are the module's (on the flight itself)."""
    copy = tmp_path / "flight"
    if method == "transformer":  # the shipped weights take 20 Hz frames: the real slice, linked
        micro = shared_path("euroc_v101_micro")
        (copy / "mav0").mkdir(parents=True)
        for entry in (micro / "mav0").iterdir():
            os.symlink(entry, copy / "mav0" / entry.name)
    else:
        shutil.copytree(flight, copy)
    options = configure_method(method, OPTIONS.get(method, []))
    if method == "vio-bias":
        first = cli_run[0]
    elif method == "self-calib":
        first = self_calib_run[0]
    else:
        first, _ = _predict(copy, method, options)
        assert first["true"] is not None  # the truth was there
    _check_pooled_scores(method, first)
    gt = copy / "mav0" / "state_groundtruth_estimate0"
    gt.unlink() if gt.is_symlink() else shutil.rmtree(gt)
    (copy / "sim_config.json").unlink(missing_ok=True)
    blind, estimate = _predict(copy, method, options)
    np.testing.assert_array_equal(blind["per_window"], first["per_window"])
    np.testing.assert_array_equal(blind["offset"], first["offset"])
    np.testing.assert_array_equal(estimate.median, first["offset"])
    assert blind["true"] is None and blind["recorded"] is None
    assert not gt.exists() and not (copy / "sim_config.json").exists()


def test_visual_ls_recovers_the_gyro_and_leaves_the_accel_alone(flight, tmp_path):
    """``visual-ls`` on the same flight: the gyro's total constant error from the frames'
    rotations, nothing subtracted from the accelerometer; the rotations are cached beside the
    recording and reused (the estimate does not change with ``--inject``: the rotations are
    the camera's)."""
    copy = tmp_path / "flight"
    shutil.copytree(flight, copy)
    summary, estimate = _predict(copy, "visual-ls")
    assert summary["method"] == "visual-ls" and summary["label"] == "total"
    assert summary["channels"] == ["gx", "gy", "gz"] and estimate.offset[3:].tolist() == [0] * 3
    bias = sensor_bias(_ground_truth(flight), *summary["span_ns"])
    true = np.add(RECORDED, INJECT)[:3] + bias[:3]
    np.testing.assert_allclose(summary["true"], true, atol=1e-12)
    assert np.all(np.abs(np.asarray(summary["offset"]) - true) < GYRO_TOLERANCE)
    assert len(list(copy.glob("visual_rotations.*.npz"))) == 1
    again, _ = _predict(copy, "visual-ls", inject=None)
    np.testing.assert_allclose(np.asarray(again["offset"]) - np.asarray(summary["offset"]),
                               -np.asarray(INJECT[:3]), atol=2e-4)


def _spy_method(seen: list, label: str) -> OffsetMethod:
    """A method that records the sequence it is given and returns its IMU's mean."""

    def estimate(sequence, options, *, progress=False):
        seen.append(sequence)
        mean = np.concatenate([sequence.imu.gyro.mean(0), sequence.imu.accel.mean(0)])
        t = sequence.imu.t_ns
        return OffsetEstimate(mean, SIX_CHANNELS[:3], mean[:3], mean[None, :3],
                              np.zeros(1), "frame", (int(t[0]), int(t[-1])), label, options)

    return OffsetMethod("spy", "records its input", lambda overrides: None, estimate)


@pytest.mark.parametrize("label", ["injected", "total"])
def test_estimators_get_no_ground_truth_and_are_scored_under_their_label(flight, monkeypatch,
                                                                          label):
    seen: list = []
    monkeypatch.setitem(METHODS, "spy", _spy_method(seen, label))
    summary, estimate = _predict(flight, "spy")
    (given,) = seen
    assert given.ground_truth is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        recorded = read_euroc(flight)
    np.testing.assert_allclose(given.imu.gyro, recorded.imu.gyro + np.asarray(INJECT[:3]),
                               atol=1e-12)
    np.testing.assert_allclose(given.imu.accel, recorded.imu.accel + np.asarray(INJECT[3:]),
                               atol=1e-12)
    true = np.add(RECORDED, INJECT)
    if label == "total":
        true = true + sensor_bias(recorded.ground_truth, *estimate.span_ns)
    assert summary["label"] == label and summary["channels"] == ["gx", "gy", "gz"]
    np.testing.assert_allclose(summary["true"], true[:3], atol=1e-12)
    np.testing.assert_allclose(summary["error"], estimate.median - true[:3], atol=1e-12)


def test_tail_median_keeps_good_items_of_the_flights_end():
    t_ns = np.arange(10, dtype=np.int64) * 1_000_000_000  # 0..9 s
    values = np.arange(20.0).reshape(10, 2)
    values[8] = np.nan
    good = np.ones(10, bool)
    good[6] = False
    used, median = tail_median(t_ns, values, good, 0.5)  # from 4.5 s on
    np.testing.assert_array_equal(used, [5, 7, 9])
    np.testing.assert_allclose(median, np.median(values[[5, 7, 9]], axis=0))
    used, median = tail_median(t_ns, values, np.zeros(10, bool), 1.0)
    assert used.size == 0 and np.all(np.isnan(median))


def test_options_reach_the_vio_config_and_refuse_what_a_method_does_not_take():
    opts = configure_method("vio-bias", ["tail_fraction=0.5", "vio.solver.max_iterations=4"])
    assert isinstance(opts, VioBiasOptions)
    assert opts.tail_fraction == 0.5 and opts.vio.solver.max_iterations == 4
    with pytest.raises(DataError, match="tail_fraction"):
        configure_method("vio-bias", ["tail_fraction=0"])
    with pytest.raises(DataError, match="'checkpoint'.*transformer"):
        configure_method("vio-bias", checkpoint="runs/x")


@pytest.mark.parametrize("argv, needles", [
    (["--method", "nope"], ["'nope'", "vio-bias", "transformer"]),
    (["--checkpoint", "runs/x"], ["'checkpoint'", "transformer"]),
    (["--set", "vio.nope=1"], ["'vio.nope'"]),
])
def test_bad_method_argument_or_key_is_one_line_exit_2(tmp_path, capsys, argv, needles):
    # the options are checked before the recording is read: any folder will do
    assert main(["calib", "predict", "--sequence", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]


def test_pooled_scores_per_channel_sensor_and_no_correction():
    from uavcal_jax.pipeline.offset_scores import NO_CORRECTION, pooled_scores

    true = np.array([[0.02, -0.01, 0.03, 0.1, -0.2, 0.05], [-0.04, 0.02, 0.01, -0.1, 0.1, 0.2]])
    err = np.array([[0.001, -0.002, 0.0, 0.01, 0.0, -0.02], [0.003, 0.0, 0.0, 0.0, 0.03, 0.0]])
    rows = [{"recording": f"r{i}", "method": "a", "channels": list(SIX_CHANNELS),
             "offset": (true[i] + err[i]).tolist(), "true": true[i].tolist(),
             "error": err[i].tolist()} for i in range(2)]
    rows += [{"recording": f"r{i}", "method": "g", "channels": ["gx", "gy", "gz"],
              "offset": [0.0, 0.0, 0.0], "true": true[i, :3].tolist(),
              "error": (-true[i, :3]).tolist()} for i in range(2)]
    rows.append({"recording": "r2", "method": "a", "channels": list(SIX_CHANNELS),
                 "offset": [0.0] * 6, "true": None, "error": None})  # truth unknown: left out
    pooled = pooled_scores(rows)
    assert list(pooled) == ["a", "g", NO_CORRECTION]
    a = pooled["a"]
    assert a["recordings"] == 2 and a["sign_f1"] == 1.0
    assert a["rmse"]["gx"] == pytest.approx(np.sqrt((0.001**2 + 0.003**2) / 2))
    assert a["gyro_rmse"] == pytest.approx(np.sqrt(np.mean(err[:, :3] ** 2)))
    assert a["accel_rmse"] == pytest.approx(np.sqrt(np.mean(err[:, 3:] ** 2)))
    assert pooled["g"]["accel_rmse"] is None and pooled["g"]["channels"] == ["gx", "gy", "gz"]
    none = pooled[NO_CORRECTION]
    assert none["accel_rmse"] == pytest.approx(np.sqrt(np.mean(true[:, 3:] ** 2)))
    assert none["sign_f1"] == 0.0
    assert "gyro_z_rms" not in a  # no method predicted a sigma
    sigma = np.array([0.01] * 3 + [0.1] * 3)
    z = pooled_scores([{**r, "sigma": sigma.tolist()} for r in rows[:2]])["a"]
    assert z["gyro_z_rms"] == pytest.approx(np.sqrt(np.mean((err[:, :3] / 0.01) ** 2)))
    assert z["accel_z_rms"] == pytest.approx(np.sqrt(np.mean((err[:, 3:] / 0.1) ** 2)))


def test_self_calib_recovers_the_gyro_through_the_vios_own_windows(flight, self_calib_run):
    """``self-calib`` on the same flight: two of the VIO's windows, their biases pinned, the
    offset found by descending through their solves; the gyro agrees with the total constant
    error as ``vio-bias``'s does (the accelerometer needs a longer flight than 4 s)."""
    summary, estimate = self_calib_run
    assert summary["method"] == "self-calib" and summary["label"] == "total"
    assert summary["item"] == "window" and summary["items"] == 2
    bias = sensor_bias(_ground_truth(flight), *summary["span_ns"])
    true = np.add(RECORDED, INJECT) + bias
    np.testing.assert_allclose(summary["true"], true, atol=1e-12)
    error = np.asarray(summary["offset"])[:3] - true[:3]
    assert np.all(np.abs(error) < SELF_CALIB_GYRO_TOLERANCE), error
    # each window alone was fitted from zero: the estimate moved the whole way (the offset
    # is 0.035 rad/s per axis and more)
    per_window = np.asarray(summary["per_window"])
    assert np.all(np.abs(per_window[:, :3] - true[:3]) < 2 * SELF_CALIB_GYRO_TOLERANCE)
    np.testing.assert_allclose(estimate.offset, np.median(per_window, axis=0))


@pytest.mark.parametrize("a", [(0.0, 0.0, 9.8), (9.8, 0.1, -0.2), (-9.8, 0.0, 0.0),
                               (3.0, -4.0, 8.0)])
def test_mounting_alignment_is_the_smallest_rotation_onto_the_training_gravity(a):
    from uavcal_jax.pipeline.transformer_offset import mounting_alignment

    train = np.array([9.7, 0.2, -0.5])
    R = mounting_alignment(np.tile(a, (5, 1)), train)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    unit = np.asarray(a) / np.linalg.norm(a)
    np.testing.assert_allclose(R @ unit, train / np.linalg.norm(train), atol=1e-12)
    # the smallest: its angle is the angle between the two, and its axis is across both
    angle = np.arccos(np.clip(unit @ train / np.linalg.norm(train), -1, 1))
    assert np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)) == pytest.approx(angle, abs=1e-9)


def test_self_calib_keeps_only_the_windows_nearest_its_targets():
    from uavcal_jax.pipeline.self_calib import NearestWindows, window_targets

    targets = window_targets(0, 30_000, 3, 2 / 3)
    np.testing.assert_array_equal(targets, [10_000, 20_000, 30_000])
    np.testing.assert_array_equal(window_targets(0, 30_000, 1, 0.5), [30_000])
    sink = NearestWindows(targets)
    for t in range(0, 30_001, 700):  # a window every 700 ns, one missing near 20_000
        if abs(t - 20_000) > 1_000:
            sink(t, f"state{t}", None, None)
    kept = sink.windows()
    assert [w[0] for w in kept] == [10_500, 18_900, 29_400]  # none before the tail's start
    assert [w[1] for w in kept] == ["state10500", "state18900", "state29400"]


def test_vio_poses_are_cached_beside_the_recording_and_give_the_metric_start(flight, tmp_path,
                                                                            monkeypatch):
    """The calibrator's metric accelerometer start: the VIO's poses of the recording, kept in
    its folder (a second call reads them back: the VIO is not run again), aligned with the
    IMU around each window. Along gravity (EuRoC's IMU x) the flight's 4 s (8 nodes)
    determine the bias within its sigma (measured 0.067 off, sigma 0.03: the whole flight's
    alignment of vio-bias is as far off), far from the zero prior."""
    from uavcal_jax.data.true_offset import sensor_bias
    from uavcal_jax.data.windows import WindowConfig, make_windows
    from uavcal_jax.pipeline.motion_inputs import sequence_poses
    from uavcal_jax.vio import pose_cache

    copy = tmp_path / "flight"
    shutil.copytree(flight, copy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence, _ = read_sequence(copy)
    poses = sequence_poses(sequence)
    assert pose_cache.pose_cache_path(copy).is_file()
    assert poses.tracked.mean() > 0.5 and poses.position.shape == (len(poses.t_ns), 3)
    monkeypatch.setattr(pose_cache, "run_vio", lambda *a, **k: pytest.fail("VIO run again"))
    again = sequence_poses(sequence)
    np.testing.assert_array_equal(again.position, poses.position)
    config = WindowConfig(duration=2.0, stride=1.0, size=(64, 40), accel_start="alignment",
                          alignment_span=DURATION_S)
    windows = make_windows(sequence, config, vio_poses=poses)
    assert windows.accel_start.shape == (len(windows), 3)
    truth = RECORDED[3] + sensor_bias(_ground_truth(copy))[3]
    error = np.abs(windows.accel_start[:, 0] - truth)
    assert np.all(error < 3.0 * windows.accel_start_std[:, 0]), (error, windows.accel_start_std)
    assert np.all(error < 0.5 * abs(truth)) and np.all(windows.accel_start_std[:, 0] < 0.05)
    half = windows.subset([1])
    np.testing.assert_array_equal(half.accel_response[0], windows.accel_response[1])
