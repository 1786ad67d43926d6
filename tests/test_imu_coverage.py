"""The IMU must cover the camera's frames (:mod:`uavcal_jax.data.imu_coverage`), checked
before any work: the real micro slice with its IMU file cut after 0.7 s is refused in one
line naming the frames without IMU, by ``uavcal run``, ``uavcal vio`` and ``uavcal calib
predict``, before the VIO starts."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
from conftest import shared_path

from uavcal_jax.cli import main
from uavcal_jax.data.imu_coverage import MAX_IMU_GAP_S, uncovered_frames

#: Where the IMU file is cut, seconds after the first frame.
CUT_S = 0.7


def test_uncovered_frames_at_the_ends_and_in_a_gap():
    frames = np.arange(0, 2_000, 50, dtype=np.int64) * 1_000_000  # 20 Hz over 2 s
    imu = np.arange(100, 1_500, 5, dtype=np.int64) * 1_000_000  # 200 Hz, 0.1-1.5 s
    gap = (imu > 600_000_000) & (imu < 600_000_000 + 2 * MAX_IMU_GAP_S * 1e9)
    bad = uncovered_frames(frames, imu[~gap])
    # before the first sample (0.0, 0.05 s), inside the gap longer than MAX_IMU_GAP_S
    # (0.6-1.1 s: 0.65-1.05 s), after the last sample (1.495 s: 1.5 s on)
    np.testing.assert_array_equal(bad, [0, 1, *range(13, 22), *range(30, 40)])
    # a frame on a sample, and gaps up to the limit, are covered
    assert uncovered_frames(imu[::10], imu).size == 0
    assert uncovered_frames(frames, np.array([], np.int64)).size == frames.size


@pytest.fixture(scope="module")
def cut_slice(tmp_path_factory):
    """The micro slice, its images linked (never copied), its IMU file cut after
    :data:`CUT_S`."""
    micro = shared_path("euroc_v101_micro")
    root = tmp_path_factory.mktemp("cut") / "micro"
    (root / "mav0" / "imu0").mkdir(parents=True)
    for entry in (micro / "mav0").iterdir():
        if entry.name != "imu0":
            os.symlink(entry, root / "mav0" / entry.name)
    shutil.copy(micro / "mav0" / "imu0" / "sensor.yaml", root / "mav0" / "imu0")
    first = int((micro / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1]
                .split(",")[0])
    lines = (micro / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    kept = [lines[0]] + [line for line in lines[1:]
                         if int(line.split(",")[0]) <= first + int(CUT_S * 1e9)]
    (root / "mav0" / "imu0" / "data.csv").write_text("\n".join(kept) + "\n")
    return root


@pytest.mark.parametrize("command, argv", [
    (["run"], ["--detector", "labels", "--out", "{out}"]),
    (["vio"], ["--out", "{out}/traj.txt"]),
    (["calib", "predict"], ["--method", "vio-bias"]),
])
def test_an_imu_cut_short_is_one_line_before_the_vio(cut_slice, tmp_path, capsys, monkeypatch,
                                                     command, argv):
    def no_vio(*args, **kwargs):
        raise AssertionError("the VIO started")

    from uavcal_jax.pipeline import run, vio_bias
    from uavcal_jax.vio import run as vio_run

    for module in (run, vio_bias, vio_run):
        monkeypatch.setattr(module, "run_vio", no_vio)
    argv = [a.format(out=tmp_path / "o") for a in argv]
    assert main([*command, "--sequence", str(cut_slice), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    # the frames after the cut: 20 Hz, the first at 0.75 s (the last sample at 0.70 s)
    assert "frames 15-94 (0.75-4.70 s)" in err[0] and "0.00-0.70 s" in err[0], err[0]
    assert str(cut_slice) in err[0]
