"""Bad input to the EuRoC reader: every case errors clearly or repairs with a warning.

All corrupted folders are built in ``tmp_path`` (small synthetic ASL folders, or copies of
parts of the real micro sequence); ``../shared/data`` is never modified.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_data_euroc import make_asl

from uavcal_jax.data import read_euroc, read_sequence
from uavcal_jax.errors import DataError, DataRepairWarning

T0 = 1_000_000_000_000_000_000


def _read(root, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = read_euroc(root, **kw)
    return seq, [str(w.message) for w in caught if issubclass(w.category, DataRepairWarning)]


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _write_lines(path: Path, lines: list[str], newline_at_end: bool = True) -> None:
    path.write_text("\n".join(lines) + ("\n" if newline_at_end else ""))


@pytest.fixture
def asl(tmp_path) -> Path:
    return make_asl(tmp_path / "seq")


# ------------------------------------------------------------------ missing folders / files


def test_missing_root(tmp_path):
    with pytest.raises(DataError, match="no such folder") as err:
        read_euroc(tmp_path / "nope")
    assert err.value.path == tmp_path / "nope"


def test_root_without_mav0(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="mav0") as err:
        read_euroc(tmp_path / "empty")
    assert str(tmp_path / "empty") in str(err.value)


def test_read_sequence_names_a_path_that_is_not_a_recording(tmp_path, asl):
    with pytest.raises(DataError, match="no such file or folder") as err:
        read_sequence(tmp_path / "nope.bag")
    assert err.value.path == tmp_path / "nope.bag"
    (tmp_path / "notes.txt").write_text("not a recording")
    with pytest.raises(DataError, match="not a recording") as err:
        read_sequence(tmp_path / "notes.txt")
    assert err.value.path == tmp_path / "notes.txt"
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="mav0") as err:
        read_sequence(tmp_path / "empty")
    assert str(tmp_path / "empty") in str(err.value)
    seq, fmt = read_sequence(asl)
    assert fmt == "euroc" and seq.name == read_euroc(asl).name


@pytest.mark.parametrize("rel", [
    "mav0/imu0",
    "mav0/imu0/data.csv",
    "mav0/imu0/sensor.yaml",
    "mav0/cam0/data.csv",
    "mav0/cam0/sensor.yaml",
    "mav0/cam1/data",
    "mav0/state_groundtruth_estimate0/data.csv",
])
def test_missing_path_named(asl, rel):
    target = asl / rel
    if target.is_dir():
        shutil.rmtree(target)
    else:
        target.unlink()
    with pytest.raises(DataError) as err:
        read_euroc(asl)
    assert err.value.path == target
    assert str(target) in str(err.value)


def test_sensor_yaml_missing_key(asl):
    path = asl / "mav0/cam0/sensor.yaml"
    path.write_text(path.read_text().replace("intrinsics:", "intrinsicz:"))
    with pytest.raises(DataError, match="intrinsics") as err:
        read_euroc(asl)
    assert err.value.path == path


def test_sensor_yaml_malformed(asl):
    path = asl / "mav0/imu0/sensor.yaml"
    path.write_text("%YAML:1.0\nrate_hz: [200\n")
    with pytest.raises(DataError, match="malformed YAML") as err:
        read_euroc(asl)
    assert err.value.path == path


# ------------------------------------------------------------------ images


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_image_named_on_load(asl, damage):
    seq, _ = _read(asl)
    path = seq.cameras["cam0"].paths[4]
    data = path.read_bytes()
    path.write_bytes({"garbage": b"this is not a png at all",
                      "truncated": data[: len(data) // 2],
                      "empty": b""}[damage])
    seq, _ = _read(asl)  # reading the folder does not decode frames 1..N
    seq.cameras["cam0"].load(3)
    with pytest.raises(DataError, match="corrupt or truncated image") as err:
        seq.cameras["cam0"].load(4)
    assert err.value.path == path


def test_image_deleted_after_read(asl):
    seq, _ = _read(asl)
    path = seq.cameras["cam1"].paths[2]
    path.unlink()
    with pytest.raises(DataError, match="missing image") as err:
        seq.cameras["cam1"].load(2)
    assert err.value.path == path


def test_image_size_disagrees_with_yaml_on_load(asl):
    seq, _ = _read(asl)
    path = seq.cameras["cam0"].paths[5]
    cv2.imwrite(str(path), np.zeros((30, 40), np.uint8))
    seq, _ = _read(asl)
    with pytest.raises(DataError) as err:
        seq.cameras["cam0"].load(5, "rgb")
    msg = str(err.value)
    assert err.value.path == path
    assert "40x30" in msg and "32x24" in msg


def test_image_size_disagrees_with_yaml_first_frame_at_read(asl):
    seq, _ = _read(asl)
    path = seq.cameras["cam1"].paths[0]
    cv2.imwrite(str(path), np.zeros((30, 40), np.uint8))
    with pytest.raises(DataError) as err:
        read_euroc(asl)
    assert err.value.path == path
    assert "40x30" in str(err.value) and "32x24" in str(err.value)


def test_frames_missing_files_dropped_with_one_warning(asl):
    seq, _ = _read(asl)
    gone = [seq.cameras["cam0"].paths[i] for i in (2, 7)]
    for p in gone:
        p.unlink()
    seq, warns = _read(asl)
    assert len(seq.cameras["cam0"]) == 8
    assert len(seq.cameras["cam1"]) == 10
    missing_warns = [w for w in warns if "image file is missing" in w]
    assert len(missing_warns) == 1
    assert all(p.name in missing_warns[0] for p in gone)
    assert "lines 4, 9" in missing_warns[0]
    with pytest.raises(DataError, match="image file is missing"):
        read_euroc(asl, strict=True)


def test_camera_gap_warns(asl):
    csv = asl / "mav0/cam0/data.csv"
    lines = _lines(csv)
    del lines[4:7]  # frames 3, 4, 5 dropped from the recording (list and files)
    _write_lines(csv, lines)
    seq, warns = _read(asl)
    assert len(seq.cameras["cam0"]) == 7
    gap_warns = [w for w in warns if "dropped frames" in w]
    assert len(gap_warns) == 1 and "cam0" in gap_warns[0] and "200.0 ms" in gap_warns[0]
    with pytest.raises(DataError, match="gaps"):
        read_euroc(asl, strict=True)


# ------------------------------------------------------------------ CSV rows


@pytest.mark.parametrize("bad", [
    "{t},0.1,0.2,0.3,0.4",               # too few fields
    "{t},0.1,0.2,0.3,0.4,0.5,0.6,0.7",   # too many
    "{t},0.1,zero,0.3,0.4,0.5,0.6",      # not a number
    "12x34,0.1,0.2,0.3,0.4,0.5,0.6",     # bad timestamp
    "{t},0.1,,0.3,0.4,0.5,0.6",          # empty field
])
def test_malformed_imu_row_names_file_and_line(asl, bad):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    t = int(lines[10].split(",")[0])
    lines[10] = bad.format(t=t)  # line 11 of the file
    _write_lines(csv, lines)
    with pytest.raises(DataError, match="malformed row") as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 11
    assert f"{csv}, line 11" in str(err.value)


def test_malformed_camera_row(asl):
    csv = asl / "mav0/cam1/data.csv"
    lines = _lines(csv)
    lines[3] = lines[3].split(",")[0]  # no filename
    _write_lines(csv, lines)
    with pytest.raises(DataError) as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 4


def test_malformed_ground_truth_row(asl):
    csv = asl / "mav0/state_groundtruth_estimate0/data.csv"
    lines = _lines(csv)
    lines[2] = lines[2].replace(",1,0,0,0,", ",1,0,oops,0,")
    _write_lines(csv, lines)
    with pytest.raises(DataError) as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 3


@pytest.mark.parametrize("newline_at_end", [False, True])
def test_truncated_last_row_dropped_with_warning(asl, newline_at_end):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    lines[-1] = lines[-1][: len(lines[-1]) // 2]  # cut off mid-write
    _write_lines(csv, lines, newline_at_end)
    seq, warns = _read(asl)
    assert len(seq.imu) == 99
    trunc = [w for w in warns if "truncated last row" in w]
    assert len(trunc) == 1 and f"line {len(lines)}" in trunc[0]
    with pytest.raises(DataError, match="truncated last row") as err:
        read_euroc(asl, strict=True)
    assert err.value.path == csv


def test_truncated_last_row_in_number(asl):
    """A last row cut inside a number ('9.8' of '9.81', '-' of '-0.1') also parses or drops."""
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    lines[-1] = lines[-1].rsplit(",", 1)[0] + ",-"
    _write_lines(csv, lines, newline_at_end=False)
    seq, warns = _read(asl)
    assert len(seq.imu) == 99 and any("truncated last row" in w for w in warns)


# ------------------------------------------------------------------ timestamps


def test_non_monotonic_timestamp(asl):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    lines[20], lines[21] = lines[21], lines[20]  # lines 21 and 22 swapped
    _write_lines(csv, lines)
    with pytest.raises(DataError, match="not increasing") as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 22


def test_non_monotonic_camera(asl):
    csv = asl / "mav0/cam0/data.csv"
    lines = _lines(csv)
    lines[5], lines[6] = lines[6], lines[5]
    _write_lines(csv, lines)
    with pytest.raises(DataError, match="not increasing") as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 7


def test_duplicate_identical_row_dropped(asl):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    lines.insert(31, lines[30])  # line 32 repeats line 31
    _write_lines(csv, lines)
    seq, warns = _read(asl)
    assert len(seq.imu) == 100
    assert np.all(np.diff(seq.imu.t_ns) > 0)
    dup = [w for w in warns if "duplicated rows" in w]
    assert len(dup) == 1 and "line 32" in dup[0]
    with pytest.raises(DataError, match="duplicated"):
        read_euroc(asl, strict=True)


def test_duplicate_camera_row_dropped(asl):
    csv = asl / "mav0/cam1/data.csv"
    lines = _lines(csv)
    lines.insert(3, lines[3])
    _write_lines(csv, lines)
    seq, warns = _read(asl)
    assert len(seq.cameras["cam1"]) == 10
    assert any("duplicated rows" in w for w in warns)


def test_duplicate_timestamp_different_values_is_error(asl):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    t = lines[30].split(",")[0]
    lines.insert(31, f"{t},9,9,9,9,9,9")
    _write_lines(csv, lines)
    with pytest.raises(DataError, match="duplicate timestamp") as err:
        read_euroc(asl)
    assert err.value.path == csv and err.value.row == 32


# ------------------------------------------------------------------ values and gaps


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
def test_non_finite_imu_rows_dropped(asl, value):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    for k in (40, 41, 77):
        parts = lines[k].split(",")
        parts[3] = value
        lines[k] = ",".join(parts)
    _write_lines(csv, lines)
    seq, warns = _read(asl)
    assert len(seq.imu) == 97
    assert np.all(np.isfinite(seq.imu.gyro)) and np.all(np.isfinite(seq.imu.accel))
    nonfinite = [w for w in warns if "NaN/inf" in w]
    assert len(nonfinite) == 1 and "lines 41, 42, 78" in nonfinite[0]
    with pytest.raises(DataError, match="NaN/inf"):
        read_euroc(asl, strict=True)


def test_imu_gap_warns_and_strict_errors(asl):
    csv = asl / "mav0/imu0/data.csv"
    lines = _lines(csv)
    del lines[50:54]  # 4 samples missing: a 25 ms gap (5 periods)
    del lines[20:22]  # 2 missing: 15 ms = 3 periods, not more than 3: not reported
    _write_lines(csv, lines)
    seq, warns = _read(asl)
    assert len(seq.imu) == 94
    gaps = [w for w in warns if "IMU gaps" in w]
    assert len(gaps) == 1 and gaps[0].startswith(str(csv))
    assert "1 IMU gaps" in gaps[0] and "25.0 ms" in gaps[0] and "~4 missing" in gaps[0]
    with pytest.raises(DataError, match="IMU gaps") as err:
        read_euroc(asl, strict=True)
    assert err.value.path == csv


def test_clean_folder_is_silent_in_strict_mode(asl):
    seq = read_euroc(asl, strict=True)
    assert len(seq.imu) == 100


@pytest.mark.realdata
def test_real_imu_corrupted_copy(euroc_micro, tmp_path):
    """The real 29k-row IMU file with one bad row in the middle: error names file and line."""
    root = tmp_path / "micro"
    (root / "mav0").mkdir(parents=True)
    shutil.copytree(euroc_micro / "mav0" / "imu0", root / "mav0" / "imu0")
    csv = root / "mav0" / "imu0" / "data.csv"
    lines = _lines(csv)
    lines[15_000] = lines[15_000][:25]
    _write_lines(csv, lines)
    with pytest.raises(DataError) as err:
        read_euroc(root)
    assert err.value.path == csv and err.value.row == 15_001
