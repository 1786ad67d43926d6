"""``uavcal simulate`` and ``uavcal demo`` from the command line."""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.cli import build_parser, main
from uavcal_jax.commands.simulate import config_from_args
from uavcal_jax.data import read_euroc
from uavcal_jax.sim.config import COLORS, SimConfig


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse: --help, usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def test_help_documents_every_option(capsys):
    code, out, _ = _run(capsys, "simulate", "--help")
    assert code == 0
    for option in ("--out", "--overwrite", "--trajectory", "--start", "--duration", "--seed",
                   "--resolution", "--color", "--camera-rate", "--imu-rate", "--no-imu-noise",
                   "--imu-offset",
                   "--no-frames", "--no-depth", "--no-targets", "--ideal-camera",
                   "--exposure", "--gain", "--no-sensor-noise", "--blur-samples", "--batch",
                   "--workers", "--body-frame", "--camera-pitch", "--follow-targets",
                   "--imu-from", "--json"):
        assert option in out, option
    assert "first timestamp" in out  # --start is relative to the file's first timestamp
    code, out, _ = _run(capsys, "demo", "--help")
    assert code == 0 and all(o in out for o in ("--out", "--seed", "--imu-offset", "--json"))


def _simulate_parser() -> argparse.ArgumentParser:
    """The ``uavcal simulate`` sub-parser of the real command line."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["simulate"]


#: ``uavcal simulate`` option -> (its value, the SimConfig field it sets, the field's value).
OPTIONS = {
    "--trajectory": ("t.txt", "trajectory", "t.txt"), "--start": ("1.5", "start", 1.5),
    "--duration": ("3", "duration", 3.0), "--seed": ("4", "seed", 4),
    "--resolution": ("64x40", "resolution", (64, 40)), "--color": ("rgb", "color", "rgb"),
    "--camera-rate": ("10", "camera_rate_hz", 10.0), "--imu-rate": ("100", "imu_rate_hz", 100.0),
    "--no-imu-noise": (None, "imu_noise", False),
    "--imu-offset": ("1,2,3,4,5,6", "imu_offset", (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)),
    "--no-frames": (None, "frames", False), "--no-depth": (None, "depth", False),
    "--no-targets": (None, "targets", False), "--ideal-camera": (None, "ideal_camera", True),
    "--exposure": ("2.5", "exposure_ms", 2.5), "--gain": ("3", "gain", 3.0),
    "--no-sensor-noise": (None, "sensor_noise", False),
    "--blur-samples": ("1", "blur_samples", 1), "--batch": ("2", "batch_size", 2),
    "--workers": ("3", "png_workers", 3), "--body-frame": ("flu", "body_frame", "flu"),
    "--camera-pitch": ("30", "camera_pitch_deg", 30.0),
    "--follow-targets": ("2", "follow_targets", 2),
    "--imu-rotation": ("1,2,3", "imu_rotation_deg", (1.0, 2.0, 3.0)),
}  # fmt: skip


def test_options_set_their_fields_and_default_to_the_sim_config():
    parser = _simulate_parser()
    defaults = SimConfig()
    assert config_from_args(parser.parse_args(["--out", "rec"])) == defaults
    argv = ["--out", "rec"]
    for option, (value, _, _) in OPTIONS.items():
        argv += [option] if value is None else [option, value]
    config = config_from_args(parser.parse_args(argv))
    assert config == SimConfig(**{name: v for _, name, v in OPTIONS.values()})
    assert all(getattr(config, name) != getattr(defaults, name) for _, name, _ in
               OPTIONS.values())  # each option changed something
    actions = {a.dest: a for a in parser._actions}
    assert tuple(actions["color"].choices) == COLORS
    # every default the help states is the dataclass value
    w, h = defaults.resolution
    shown = {"start": f"{defaults.start:g}", "duration": f"{defaults.duration:g}",
             "seed": str(defaults.seed), "resolution": f"{w}x{h}", "color": defaults.color,
             "camera_rate_hz": f"{defaults.camera_rate_hz:g}",
             "imu_rate_hz": f"{defaults.imu_rate_hz:g}",
             "exposure_ms": f"{defaults.exposure_ms:g}", "gain": f"{defaults.gain:g}",
             "blur_samples": str(defaults.blur_samples), "batch_size": str(defaults.batch_size),
             "png_workers": str(defaults.png_workers)}
    for dest, text in shown.items():
        assert f"[default: {text}]" in actions[dest].help, dest
    assert defaults.imu_offset is None and "[default: none]" in actions["imu_offset"].help


def test_camera_options_set_the_config():
    parser = _simulate_parser()
    defaults = SimConfig()
    assert not defaults.ideal_camera and defaults.sensor_noise and defaults.blur_samples > 1
    args = parser.parse_args(["--out", "rec", "--ideal-camera", "--exposure", "2.5", "--gain",
                              "3", "--no-sensor-noise", "--blur-samples", "1"])
    config = config_from_args(args)
    assert (config.ideal_camera, config.exposure_ms, config.gain, config.sensor_noise,
            config.blur_samples) == (True, 2.5, 3.0, False, 1)


def test_imu_offset_option_sets_the_config():
    parser = _simulate_parser()
    args = parser.parse_args(["--out", "rec", "--imu-offset=-0.02,0.01,0.03,0.2,-0.1,1e-3"])
    assert config_from_args(args).imu_offset == (-0.02, 0.01, 0.03, 0.2, -0.1, 0.001)


def _read_csv(path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64)


def test_imu_offset_is_added_to_the_written_imu(capsys, tmp_path):
    offset = (-0.02, 0.01, 0.03, 0.2, -0.1, 0.15)
    common = ["--no-frames", "--duration", "1", "--seed", "2", "--json"]
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "clean"), *common)
    assert code == 0, err
    code, out, err = _run(capsys, "simulate", "--out", str(tmp_path / "miscal"), *common,
                          "--imu-offset=" + ",".join(map(str, offset)))
    assert code == 0, err
    assert json.loads(out.strip().splitlines()[-1])["imu_offset"] == list(offset)
    resolved = json.loads((tmp_path / "miscal" / "sim_config.json").read_text())
    assert resolved["config"]["imu_offset"] == list(offset)
    assert json.loads((tmp_path / "clean" / "sim_config.json").read_text()
                      )["config"]["imu_offset"] is None
    clean = _read_csv(tmp_path / "clean" / "mav0" / "imu0" / "data.csv")
    miscal = _read_csv(tmp_path / "miscal" / "mav0" / "imu0" / "data.csv")
    np.testing.assert_array_equal(miscal[:, 0], clean[:, 0])  # same timestamps
    # the CSV holds round-trip reprs: the difference is the offset to float64 rounding
    np.testing.assert_allclose(miscal[:, 1:] - clean[:, 1:],
                               np.broadcast_to(offset, clean[:, 1:].shape), rtol=0, atol=1e-13)


def test_imu_rotation_turns_the_imu_and_keeps_the_flight_and_frames(capsys, tmp_path):
    """``--imu-rotation``: the same flight seen by the same cameras (frames identical), the
    IMU's samples and the ground truth's orientations in the turned frame (``R_WI = R_WB
    R_BI``, samples ``R_BI^T`` of the old ones), the cameras' ``T_BS`` to match."""
    from scipy.spatial.transform import Rotation

    rotvec_deg = (0.0, -90.0, 30.0)
    # an IMU without errors (the scale and misalignment are the IMU's own axes': turned with it)
    common = ["--duration", "0.3", "--resolution", "64x40", "--no-imu-noise", "--ideal-sensors",
              "--no-depth", "--seed", "3", "--json"]
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "a"), *common)
    assert code == 0, err
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "b"), *common,
                        "--imu-rotation=" + ",".join(map(str, rotvec_deg)))
    assert code == 0, err
    R_BI = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    a, b = read_euroc(tmp_path / "a"), read_euroc(tmp_path / "b")
    np.testing.assert_allclose(b.imu.gyro, a.imu.gyro @ R_BI, atol=1e-9)
    np.testing.assert_allclose(b.imu.accel, a.imu.accel @ R_BI, atol=1e-9)
    np.testing.assert_allclose(b.ground_truth.position, a.ground_truth.position, atol=1e-9)
    R_a = Rotation.from_quat(a.ground_truth.quaternion[:, [1, 2, 3, 0]]).as_matrix()
    R_b = Rotation.from_quat(b.ground_truth.quaternion[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(R_b, R_a @ R_BI, atol=1e-9)
    for cam in ("cam0", "cam1"):
        T_a, T_b = a.camera(cam).calibration.T_BS, b.camera(cam).calibration.T_BS
        np.testing.assert_allclose(T_b[:3, :3], R_BI.T @ T_a[:3, :3], atol=1e-12)
        np.testing.assert_allclose(T_b[:3, 3], R_BI.T @ T_a[:3, 3], atol=1e-12)
        for k in range(len(a.camera(cam))):
            np.testing.assert_array_equal(a.camera(cam).load(k), b.camera(cam).load(k))
    resolved = json.loads((tmp_path / "b" / "sim_config.json").read_text())
    assert resolved["config"]["imu_rotation_deg"] == list(rotvec_deg)
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "c"),
                        "--imu-rotation", "1,2")
    assert code == 2 and "X,Y,Z" in err


@pytest.mark.parametrize("bad", ["1,2,3,4,5", "1,2,3,4,5,6,7", "nan,0,0,0,0,0",
                                 "0,0,inf,0,0,0", "a,b,c,d,e,f", "0.1 0.2 0.3 0 0 0"])
def test_bad_imu_offset_is_a_usage_error(capsys, tmp_path, bad):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--no-frames",
                        f"--imu-offset={bad}")
    assert code == 2 and "usage" in err and "--imu-offset" in err
    assert not (tmp_path / "rec").exists()


def test_exposure_longer_than_a_frame_is_one_clear_line(capsys, tmp_path):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--exposure", "60",
                        "--duration", "1")
    assert code == 2 and "exposure" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "rec").exists()


def test_no_frames_json(capsys, tmp_path):
    code, out, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--no-frames",
                          "--duration", "1", "--seed", "2", "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["imu"] == 201 and "frames" not in summary
    assert not (tmp_path / "rec" / "mav0" / "cam0").exists()
    seq = read_euroc(tmp_path / "rec")
    assert len(seq.imu) == 201 and seq.cameras == {}


def test_missing_trajectory_is_one_clear_line(capsys, tmp_path):
    missing = tmp_path / "no_such_flight.txt"
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--trajectory",
                        str(missing), "--no-frames")
    assert code == 2
    assert str(missing) in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "rec").exists()


def test_unreadable_trajectory(capsys, tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("# t tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\nnot a pose line at all\n"
                   "3.0 0 0 0 0 0 0 1\n")
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--trajectory",
                        str(bad), "--no-frames")
    assert code == 2 and str(bad) in err and len(err.strip().splitlines()) == 1


@pytest.mark.realdata
def test_start_past_the_file(capsys, tmp_path):
    path = shared_path("trajectories", "euroc", "V1_01_easy.txt")
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--trajectory",
                        str(path), "--start", "500", "--no-frames")
    assert code == 2 and str(path) in err and "past the end" in err
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--trajectory",
                        str(path), "--start", "140", "--duration", "30", "--no-frames")
    assert code == 2 and str(path) in err


def test_start_needs_a_trajectory(capsys, tmp_path):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--start", "3")
    assert code == 2 and "--trajectory" in err


def test_non_empty_output_needs_overwrite(capsys, tmp_path):
    out = tmp_path / "rec"
    out.mkdir()
    (out / "something").write_text("x")
    code, _, err = _run(capsys, "simulate", "--out", str(out), "--no-frames", "--duration", "1")
    assert code == 2 and str(out) in err and "--overwrite" in err
    assert (out / "something").exists()


@pytest.mark.parametrize("bad", [["--resolution", "big"], ["--duration", "-1"],
                                 ["--color", "sepia"], ["--exposure", "0"],
                                 ["--blur-samples", "0"], ["--gain", "-2"]])
def test_bad_options_are_usage_errors(capsys, tmp_path, bad):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), *bad)
    assert code == 2 and "usage" in err


#: The demo's car, filtered median error bound, m: measured 0.39 m (issue 42 asks 0.5) with the
#: shipped weights (fine-tuned on flights rendered with the realistic defaults), their boxes
#: redrawn from the depth over a ground plane (``refine``) and ByteTrack's two rounds (0.47 m
#: with one, and one ground height). Small changes upstream move it by about 0.1 m (a few pixels
#: of box turn the box model's heading), hence the margin.
DEMO_CAR_MEDIAN_M = 0.6
#: The demo's VIO ATE bound, m: measured 0.049 m. The shipped detector masks the VIO's features
#: on its boxes scoring 0.25 or more, and these weights leave more of the moving car's features
#: in than the previous ones (0.021 m); at 0.4 the ATE is 0.22 m.
DEMO_ATE_M = 0.06


def test_demo_json(capsys, tmp_path):
    """The main job end to end, as a fresh install runs it (``uavcal demo --json``)."""
    out = tmp_path / "demo"
    code, printed, err = _run(capsys, "demo", "--json", "--out", str(out))
    assert code == 0, err
    result = json.loads(printed.strip().splitlines()[-1])
    assert result["out"] == str(out)
    assert list(result["steps"]) == ["simulate", "read", "calibrate"]
    assert set(result["step_seconds"]) == {"simulate", "read", "calibrate", "run", "total"}
    summary = result["steps"]["read"]
    assert set(summary["cameras"]) == {"cam0", "cam1"}
    assert set(summary["depth"]) == {"depth0", "depth1"}
    assert summary["imu"]["samples"] == 2401  # 12 s at 200 Hz
    assert summary["cameras"]["cam0"]["frames"] == 241
    assert summary["targets"]["present"]
    assert summary["warnings"] == []
    recording = out / "recording"
    assert (recording / "mav0" / "cam0" / "data.csv").is_file()
    # The calibrate step: the truth is the offset written into the IMU (sim_config.json
    # records it) plus the simulated sensor's own bias (the ground truth's bias columns)
    calib = result["steps"]["calibrate"]
    recorded = json.loads((recording / "sim_config.json").read_text())["config"]["imu_offset"]
    np.testing.assert_allclose(calib["injected"], recorded)
    gt = read_euroc(recording).ground_truth
    bias = np.concatenate([gt.bias_gyro, gt.bias_accel], axis=1).mean(axis=0)
    true = np.add(recorded, bias)
    np.testing.assert_allclose(calib["true"], true, atol=1e-12)
    methods = calib["methods"]
    assert list(methods) == ["vio-bias", "visual-ls", "transformer"]
    for m in methods.values():
        # each scored against the truth under its own label and span (vio-bias: the tail of
        # the flight), which differs from the whole flight's only by the sensor bias's walk
        np.testing.assert_allclose(np.subtract(m["offset"], m["true"]), m["error"], atol=1e-12)
        np.testing.assert_allclose(m["true"], calib["true"], atol=0.02)
    # blind estimates (no ground truth read) of the gyro within 5e-3 rad/s per axis
    for name in ("vio-bias", "visual-ls"):
        assert np.all(np.abs(methods[name]["error"][:3]) < 5e-3), (name, methods[name])
    # the run removes the default method's estimate: closer to the truth than no correction
    # on every channel (measured: the gyro's errors 1-2 % of the truth, the accelerometer's
    # 4-15 %)
    offset = result["offset"]
    assert offset["method"] == "vio-bias"
    np.testing.assert_allclose(offset["estimate"], methods["vio-bias"]["offset"])
    error = np.subtract(offset["estimate"], offset["true"])
    assert np.all(np.abs(error) < 0.4 * np.abs(offset["true"])), (error, offset["true"])
    # the run: a pose on every frame, the VIO on track, the car found and located
    assert result["vio"]["poses"] == result["vio"]["frames"] == 241
    assert result["ate_m"]["rmse"] < DEMO_ATE_M
    assert result["detections"]["followed_class"] == "car"
    assert result["detections"]["true_track"] is not None  # the followed track is a labelled car
    # one car drives past a standing person: the run never follows another target
    assert result["detections"]["target_switches"] == 0
    filtered = result["target_error_m"]["filtered"]
    assert filtered["median"] <= DEMO_CAR_MEDIAN_M and np.isfinite(filtered["rmse"]), filtered
    assert all(np.isfinite(v["mean"]) for v in result["ms_per_frame"].values() if v)
    run = out / "run"
    for name in ("trajectory.txt", "targets.csv", "setpoints.csv", "metrics.json",
                 "config.json", "top_view.png", "frames.png", "localisation_error.png"):
        assert (run / name).is_file(), name


def test_demo_refuses_a_folder_with_files(capsys, tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    code, _, err = _run(capsys, "demo", "--out", str(tmp_path))
    assert code == 2 and str(tmp_path) in err and "--out" in err
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_rgb_frames_small_resolution(capsys, tmp_path):
    code, out, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--color", "rgb",
                          "--resolution", "64x40", "--duration", "0.2", "--no-depth", "--json")
    assert code == 0, err
    assert json.loads(out.strip().splitlines()[-1])["frames"] == 5
    seq = read_euroc(tmp_path / "rec")
    assert seq.depth == {}
    assert seq.cameras["cam1"].calibration.resolution == (64, 40)
    raw = cv2.imread(str(seq.cameras["cam1"].paths[0]), cv2.IMREAD_UNCHANGED)
    assert raw.shape == (40, 64, 3) and raw.dtype == np.uint8


def test_set_applies_after_the_options():
    parser = _simulate_parser()
    args = parser.parse_args(["--out", "rec", "--duration", "3", "--seed", "4", "--set",
                              "duration=2", "resolution=376x240", "--set", "imu_offset=none"])
    config = config_from_args(args)
    assert (config.duration, config.seed, config.resolution, config.imu_offset) == (
        2.0, 4, (376, 240), None)
    assert config_from_args(parser.parse_args(["--out", "rec", "--set", "gain=2"])
                            ) == SimConfig(gain=2.0)


def test_set_unknown_key_exits_2_naming_it(capsys, tmp_path):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), "--no-frames",
                        "--set", "no_such_key=1")
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "no_such_key" in err
    assert not (tmp_path / "rec").exists()


def test_set_values_are_in_sim_config_json(capsys, tmp_path):
    out = tmp_path / "rec"
    code, _, err = _run(capsys, "simulate", "--out", str(out), "--no-frames", "--duration",
                        "1", "--json", "--set", "imu_rate_hz=100", "seed=5")
    assert code == 0, err
    resolved = json.loads((out / "sim_config.json").read_text())["config"]
    assert (resolved["imu_rate_hz"], resolved["seed"], resolved["duration"]) == (100.0, 5, 1.0)
    assert len(read_euroc(out).imu) == 101  # the --set rate was simulated (both ends)
