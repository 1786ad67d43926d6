"""``uavcal simulate`` and ``uavcal demo`` from the command line."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.cli import main
from uavcal_jax.data import read_euroc


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
                   "--no-frames", "--no-depth", "--no-targets", "--batch", "--workers",
                   "--json"):
        assert option in out, option
    assert "first timestamp" in out  # --start is relative to the file's first timestamp
    code, out, _ = _run(capsys, "demo", "--help")
    assert code == 0 and "--keep" in out and "--json" in out


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
                                 ["--color", "sepia"]])
def test_bad_options_are_usage_errors(capsys, tmp_path, bad):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "rec"), *bad)
    assert code == 2 and "usage" in err


def test_demo_json_keep(capsys, tmp_path):
    keep = tmp_path / "demo"
    code, out, err = _run(capsys, "demo", "--json", "--keep", str(keep))
    assert code == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert [k for k in result if k != "seconds"] == ["simulate", "read"]
    summary = result["read"]
    assert set(summary["cameras"]) == {"cam0", "cam1"}
    assert set(summary["depth"]) == {"depth0", "depth1"}
    assert summary["imu"]["samples"] == 601  # 3 s at 200 Hz
    assert summary["cameras"]["cam0"]["frames"] == 61
    assert summary["targets"]["present"]
    assert summary["warnings"] == []
    assert (keep / "mav0" / "cam0" / "data.csv").is_file()
    assert (keep / "sim_config.json").is_file()


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
