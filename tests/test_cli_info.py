"""``uavcal info`` through ``uavcal_jax.cli.main``."""

from __future__ import annotations

import json

import pytest
from test_data_euroc import make_asl

from uavcal_jax.cli import main


def _info_json(capsys, *args) -> dict:
    assert main(["info", *map(str, args), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1  # one JSON object on one line
    return json.loads(out[0])


@pytest.mark.realdata
def test_info_micro_json(euroc_micro, capsys):
    s = _info_json(capsys, euroc_micro)
    assert s["sequence"] == "euroc_v101_micro" and s["format"] == "euroc"
    assert sorted(s["cameras"]) == ["cam0", "cam1"]
    for name, intr in (("cam0", [458.654, 457.296, 367.215, 248.375]),
                       ("cam1", [457.587, 456.134, 379.999, 255.238])):
        cam = s["cameras"][name]
        assert cam["frames"] == 95
        assert cam["rate_hz_nominal"] == 20.0
        assert cam["rate_hz_measured"] == pytest.approx(20.0, rel=1e-4)
        assert cam["duration_s"] == pytest.approx(4.7, abs=1e-6)
        assert cam["n_gaps"] == 0
        assert cam["calibration"]["intrinsics"] == intr
        assert cam["calibration"]["resolution"] == [752, 480]
        assert len(cam["calibration"]["T_BS"]) == 4
    imu = s["imu"]
    assert imu["samples"] == 29_120
    assert imu["rate_hz_nominal"] == 200.0
    assert imu["rate_hz_measured"] == pytest.approx(200.0, rel=1e-3)
    assert imu["n_gaps"] == 0 and imu["gaps"] == []
    assert imu["calibration"]["gyroscope_noise_density"] == 1.6968e-04
    assert imu["calibration"]["accelerometer_random_walk"] == 3.0e-3
    assert imu["duration_s"] == pytest.approx(145.6, abs=0.1)
    gt = s["ground_truth"]
    assert gt["present"] is True and gt["states"] == 2_895
    assert gt["rate_hz_measured"] == pytest.approx(20.0, rel=1e-3)
    assert s["targets"] == {"present": False}
    assert s["depth"] == {}
    assert len(s["warnings"]) == 1 and "cam1" in s["warnings"][0]


@pytest.mark.realdata
def test_info_micro_text(euroc_micro, capsys):
    assert main(["info", str(euroc_micro)]) == 0
    out = capsys.readouterr().out
    assert "cam0: 95 frames" in out and "imu0: 29120 samples" in out
    assert "ground truth: 2895 states" in out
    assert "458.654" in out


def test_info_missing_folder(tmp_path, capsys):
    missing = tmp_path / "no_such_sequence"
    assert main(["info", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "uavcal info: error:" in err and str(missing) in err
    assert len(err.strip().splitlines()) == 1


def test_info_gaps_and_strict(tmp_path, capsys):
    root = make_asl(tmp_path / "seq")
    csv = root / "mav0/imu0/data.csv"
    lines = csv.read_text().splitlines()
    del lines[50:55]  # 5 samples missing: 30 ms gap
    csv.write_text("\n".join(lines) + "\n")
    s = _info_json(capsys, root)
    assert s["imu"]["samples"] == 95 and s["imu"]["n_gaps"] == 1
    gap = s["imu"]["gaps"][0]
    assert gap["duration_s"] == pytest.approx(0.030) and gap["missing"] == 5
    assert any("IMU gaps" in w for w in s["warnings"])
    assert s["cameras"]["cam0"]["frames"] == 10
    assert main(["info", str(root), "--strict"]) == 2
    assert "IMU gaps" in capsys.readouterr().err


def test_info_rosbag(tmp_path, capsys):
    from test_data_rosbag import write_bag

    path = tmp_path / "flight.bag"
    write_bag(path, 1)
    s = _info_json(capsys, path)
    assert s["format"] == "rosbag" and s["sequence"] == "flight"
    assert s["imu"]["samples"] == 50 and s["imu"]["calibration"] is None
    assert s["imu"]["rate_hz_measured"] == pytest.approx(200.0)
    assert s["cameras"]["cam0"]["frames"] == 6
    assert s["cameras"]["cam0"]["calibration"]["intrinsics"] == [None] * 4  # unknown
    assert s["ground_truth"]["present"] is False
    assert main(["info", str(path)]) == 0
    assert "fu fv cu cv = unknown" in capsys.readouterr().out
    empty = tmp_path / "noimu.bag"
    write_bag(empty, 1, imu=False)
    assert main(["info", str(empty)]) == 2
    assert "no sensor_msgs/msg/Imu topic" in capsys.readouterr().err
