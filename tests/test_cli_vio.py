"""``uavcal vio`` from the command line: outputs, offsets, settings (``--set``, ``--config``,
OUT.config.json), bad input."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.cli import main
from uavcal_jax.data.offset_json import read_offset_json, write_offset_json
from uavcal_jax.data.tum import read_tum
from uavcal_jax.data.vio_frames import FRAME_COLUMNS
from uavcal_jax.errors import DataError


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["vio", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for option in ("--sequence", "--out", "--offsets", "--plot", "--json", "--set", "--config"):
        assert option in out


def test_short_run_writes_tum_frames_and_summary(capsys, tmp_path):
    root = shared_path("euroc_v101_micro")
    offsets = write_offset_json(tmp_path / "offsets.json", np.zeros(6))
    traj = tmp_path / "traj.txt"
    code, out, err = _run(capsys, "vio", "--sequence", str(root), "--out", str(traj),
                          "--max-frames", "12", "--offsets", str(offsets), "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == summary["poses"] == 12 and summary["nan_poses"] == 0
    est = read_tum(traj)
    assert len(est) == 12 and np.all(np.isfinite(est.position))
    # the same timestamps as the left camera's first frames
    from uavcal_jax.data.euroc import read_euroc

    with pytest.warns(Warning):
        cam0 = read_euroc(root).camera("cam0")
    np.testing.assert_array_equal(est.t_ns, cam0.t_ns[:12])
    with (tmp_path / "traj.txt.frames.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == FRAME_COLUMNS and len(rows) == 13
    # against the ground truth: a hover, millimetres
    assert summary["ate_m"]["rmse"] < 0.02


def test_unknown_setting_is_a_one_line_error_naming_the_key(capsys, tmp_path):
    # settings are checked before the recording is read: any existing folder will do
    code, _, err = _run(capsys, "vio", "--sequence", str(tmp_path), "--out",
                        str(tmp_path / "t.txt"), "--set", "nope=1")
    assert code == 2 and err.count("\n") == 1 and "'nope'" in err, err
    assert "solver.max_iterations" in err, "the valid keys are listed"
    code, _, err = _run(capsys, "vio", "--sequence", str(tmp_path), "--out",
                        str(tmp_path / "t.txt"), "--set", "frontend.equalize=gamma")
    assert code == 2 and err.count("\n") == 1 and "equalize" in err, err
    assert not (tmp_path / "t.txt").exists()


def test_set_changes_the_run_and_config_json_repeats_it(capsys, tmp_path):
    root = shared_path("euroc_v101_micro")
    offset = np.array([0.001, -0.002, 0.0, 0.01, 0.0, -0.01])
    offsets = write_offset_json(tmp_path / "offsets.json", offset)
    traj = tmp_path / "traj.txt"
    # too few tracked corners for any frame: every frame becomes a keyframe (with the defaults
    # only the first of these six is one: the slice is a hover)
    code, out, err = _run(capsys, "vio", "--sequence", str(root), "--out", str(traj),
                          "--max-frames", "6", "--offsets", str(offsets),
                          "--set", "keyframe.min_tracked=1000", "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == summary["keyframes"] == 6
    written = json.loads((tmp_path / "traj.txt.config.json").read_text())
    assert summary["config"] == str(tmp_path / "traj.txt.config.json")
    assert written["keyframe"]["min_tracked"] == 1000
    assert written["cost"]["focal_px"] == 458.654, "resolved from the left camera (cam0's fx)"
    inputs = written["inputs"]
    assert inputs["max_frames"] == 6 and inputs["left"] == "cam0" and inputs["right"] == "cam1"
    np.testing.assert_array_equal(inputs["imu_offset"], offset)
    assert inputs["overrides"] == ["keyframe.min_tracked=1000"]
    # the file alone repeats the run: settings, offset and frame count
    again = tmp_path / "again.txt"
    code, out, err = _run(capsys, "vio", "--sequence", str(root), "--out", str(again),
                          "--config", str(tmp_path / "traj.txt.config.json"), "--json")
    assert code == 0, err
    assert json.loads(out.strip().splitlines()[-1])["keyframes"] == 6
    first, second = read_tum(traj), read_tum(again)
    np.testing.assert_array_equal(first.t_ns, second.t_ns)
    np.testing.assert_array_equal(first.position, second.position)
    repeated = json.loads((tmp_path / "again.txt.config.json").read_text())
    assert {k: v for k, v in repeated.items() if k != "inputs"} == {
        k: v for k, v in written.items() if k != "inputs"}


def test_missing_sequence_and_bad_offsets_are_one_line_errors(capsys, tmp_path):
    code, _, err = _run(capsys, "vio", "--sequence", str(tmp_path / "nowhere"), "--out",
                        str(tmp_path / "t.txt"))
    assert code == 2 and "no such file" in err and err.count("\n") == 1
    bad = tmp_path / "bad.json"
    bad.write_text('{"offset": [1, 2, 3]}')
    root = shared_path("euroc_v101_micro")
    code, _, err = _run(capsys, "vio", "--sequence", str(root), "--out", str(tmp_path / "t.txt"),
                        "--offsets", str(bad))
    assert code == 2 and "bad.json" in err and "6 finite numbers" in err


@pytest.mark.parametrize("text, message", [
    ("not json", "not a readable JSON"),
    ('{"bias": [0, 0, 0, 0, 0, 0]}', "'offset' key"),
    ('{"offset": [0, 0, 0, 0, 0, NaN]}', "6 finite numbers"),
    ('{"offset": "abc"}', "6 "),
])
def test_offset_file_errors(tmp_path, text, message):
    path = tmp_path / "o.json"
    path.write_text(text)
    with pytest.raises(DataError, match=message):
        read_offset_json(path)
    with pytest.raises(DataError, match="not found"):
        read_offset_json(tmp_path / "absent.json")


def test_offset_file_round_trip(tmp_path):
    offset = np.array([0.01, -0.02, 0.03, 0.1, -0.2, 0.3])
    path = write_offset_json(tmp_path / "o.json", offset, windows=3)
    np.testing.assert_array_equal(read_offset_json(path), offset)
    assert json.loads(path.read_text())["windows"] == 3
