"""Hybrid recordings (uavcal_jax.sim.hybrid): the real EuRoC V1_01 IMU and ground truth with
simulated stereo frames rendered along the real flight, on the real camera clock."""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest
from conftest import shared_path
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.errors import DataError
from uavcal_jax.sim import frames as sim_frames
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.hybrid import simulate_hybrid, trigger_phase
from uavcal_jax.sim.trajectory_fit import fit_tum_trajectory

START, DURATION = 2.0, 3.0
#: Small, sharp frames: the test is about timestamps, poses and the copied IMU, not images.
SMALL = SimConfig(resolution=(160, 96), ideal_camera=True, batch_size=4)
#: V1_01's ground-truth gyro bias, rad/s (EuRoC's estimate; steady over the flight).
V101_GYRO_BIAS = np.array([-0.0022, 0.0211, 0.0765])


def _read_quietly(path):
    with warnings.catch_warnings():  # the real cam1 lists 4 frames it does not ship
        warnings.simplefilter("ignore")
        return read_euroc(path)


@pytest.fixture(scope="module")
def real():
    return _read_quietly(shared_path("euroc_v101_micro"))


@pytest.fixture(scope="module")
def hybrid(tmp_path_factory, real):
    """A 3 s hybrid, with the body poses the renderer was given recorded (``T_WB`` per frame
    time, from :func:`uavcal_jax.sim.frames.body_poses`)."""
    calls: list[tuple[np.ndarray, np.ndarray]] = []
    spied = sim_frames.body_poses

    def recording(traj, t_ns):
        out = spied(traj, t_ns)
        calls.append((np.array(t_ns), out))
        return out

    out = tmp_path_factory.mktemp("hybrid") / "h"
    with pytest.MonkeyPatch.context() as mp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mp.setattr(sim_frames, "body_poses", recording)
        report = simulate_hybrid(real.root, out, SMALL, start=START, duration=DURATION,
                                 progress=False)
    seq, fmt = read_sequence(out)
    assert fmt == "euroc"
    return report, seq, calls


def test_imu_and_ground_truth_are_the_real_rows(real, hybrid):
    report, seq, _ = hybrid
    t0 = real.imu.t_ns[0] + int(START * 1e9)
    i0 = int(np.searchsorted(real.imu.t_ns, t0))
    n = len(seq.imu)
    assert n == int(DURATION * 200) + 1
    # bit-exact: same int64 timestamps, same float64 values
    np.testing.assert_array_equal(seq.imu.t_ns, real.imu.t_ns[i0:i0 + n])
    np.testing.assert_array_equal(seq.imu.gyro, real.imu.gyro[i0:i0 + n])
    np.testing.assert_array_equal(seq.imu.accel, real.imu.accel[i0:i0 + n])
    gt, rgt = seq.ground_truth, real.ground_truth
    j = np.flatnonzero(np.isin(rgt.t_ns, gt.t_ns))
    assert len(j) == len(gt) >= int(DURATION * 20)  # V1_01's micro ground truth is 20 Hz
    assert np.all(np.diff(j) == 1)
    for field in ("t_ns", "position", "quaternion", "velocity", "bias_gyro", "bias_accel"):
        np.testing.assert_array_equal(getattr(gt, field), getattr(rgt, field)[j])
    # the real sensor's noise model, not the simulator's
    assert seq.imu_calibration.noise == real.imu_calibration.noise
    rec = json.loads((report.root / "sim_config.json").read_text())
    assert rec["flight"]["source"] == "hybrid" and rec["imu_noise"] is None
    assert rec["config"]["imu_offset"] is None and recorded_imu_offset(report.root) is None
    assert rec["flight"]["t_start_ns"] == int(seq.imu.t_ns[0])


def test_frames_are_on_the_real_camera_clock(real, hybrid):
    _, seq, _ = hybrid
    cam_t = seq.cameras["cam0"].t_ns
    np.testing.assert_array_equal(seq.cameras["cam1"].t_ns, cam_t)
    # every 10th real IMU sample, with the phase of the real frames ...
    idx = np.searchsorted(real.imu.t_ns, cam_t)
    np.testing.assert_array_equal(real.imu.t_ns[idx], cam_t)
    assert np.all(np.diff(idx) == 10)
    assert trigger_phase(real.imu.t_ns, real.cameras["cam0"].t_ns, 10) == idx[0] % 10
    # ... so the real frames in the span are among them, and the span is covered throughout
    real_t = real.cameras["cam0"].t_ns
    in_span = real_t[(real_t >= seq.imu.t_ns[0]) & (real_t <= seq.imu.t_ns[-1])]
    assert len(in_span) > 10 and np.all(np.isin(in_span, cam_t))
    assert cam_t[0] == seq.imu.t_ns[0] and seq.imu.t_ns[-1] - cam_t[-1] < 50_000_000
    assert len(cam_t) == int(DURATION * 20) + 1


def test_reads_back_with_depth_targets_and_real_bias(hybrid):
    _, seq, _ = hybrid
    assert set(seq.cameras) == {"cam0", "cam1"} and set(seq.depth) == {"depth0", "depth1"}
    np.testing.assert_array_equal(seq.depth["depth0"].t_ns, seq.cameras["cam0"].t_ns)
    img = seq.cameras["cam0"].load(len(seq.cameras["cam0"]) // 2)
    depth = seq.depth["depth0"].load(0)
    assert img.shape == (96, 160) and img.std() > 5  # a textured room, not a blank frame
    assert np.median(depth[depth > 0]) > 0.3 and (depth > 0).mean() > 0.9
    assert seq.targets is not None
    bias = seq.ground_truth.bias_gyro.mean(axis=0)
    np.testing.assert_allclose(bias, V101_GYRO_BIAS, atol=1.5e-3)
    assert np.ptp(seq.ground_truth.bias_gyro, axis=0).max() < 1e-3  # steady


def test_frame_poses_follow_the_real_flight(real, hybrid):
    """The body pose each frame was rendered at is the fitted trajectory at the frame's time,
    and within a millimetre (and 0.3 degrees) of the real ground truth's row at that time."""
    _, seq, calls = hybrid
    cam_t = seq.cameras["cam0"].t_ns
    used = [T for t, T in calls if t.shape == cam_t.shape and np.array_equal(t, cam_t)]
    assert used, "render_frames did not evaluate the body poses at the frame times"
    T_WB = used[0]
    t0, t1 = int(seq.imu.t_ns[0]), int(seq.imu.t_ns[-1])
    fit = fit_tum_trajectory(real.ground_truth, start=t0 * 1e-9, duration=(t1 - t0) * 1e-9)
    np.testing.assert_allclose(T_WB, sim_frames.body_poses(fit, cam_t), atol=1e-9)

    gt = real.ground_truth
    # the ground truth's rows at frame times (its clock is up to 256 ns off the IMU's)
    k = np.minimum(np.searchsorted(gt.t_ns, cam_t - 1_000), len(gt) - 1)
    near = np.abs(gt.t_ns[k] - cam_t) < 1_000
    assert near.sum() >= len(cam_t) - 1
    dp = np.linalg.norm(T_WB[near, :3, 3] - gt.position[k[near]], axis=1)
    R_gt = Rotation.from_quat(gt.quaternion[k[near]][:, [1, 2, 3, 0]])
    angle = (R_gt.inv() * Rotation.from_matrix(T_WB[near, :3, :3])).magnitude()
    assert dp.max() < 1e-3, dp.max()
    assert np.degrees(angle.max()) < 0.3


def test_imu_offset_is_added_to_the_real_samples(real, tmp_path):
    offset = (0.01, -0.02, 0.03, 0.1, -0.2, 0.3)
    config = SimConfig(frames=False, imu_offset=offset)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = simulate_hybrid(real.root, tmp_path / "o", config, start=1.0, duration=0.5,
                                 progress=False)
    seq = read_euroc(report.root)
    i0 = int(np.searchsorted(real.imu.t_ns, seq.imu.t_ns[0]))
    n = len(seq.imu)
    np.testing.assert_allclose(seq.imu.gyro - real.imu.gyro[i0:i0 + n], np.tile(offset[:3],
                               (n, 1)), atol=1e-12)
    np.testing.assert_allclose(seq.imu.accel - real.imu.accel[i0:i0 + n], np.tile(offset[3:],
                               (n, 1)), atol=1e-12)
    np.testing.assert_array_equal(recorded_imu_offset(report.root), offset)
    assert (i0 - trigger_phase(
        real.imu.t_ns, real.cameras["cam0"].t_ns, 10)) % 10 == 0  # starts on a trigger


def test_missing_imu_or_ground_truth_is_a_data_error(real, tmp_path):
    """One line naming the folder and what is missing; nothing written."""
    src = real.root / "mav0"
    imu_rows = (src / "imu0" / "data.csv").read_text().splitlines()
    cases = {"no_gt": ("imu0", "no ground truth"), "empty_imu": ("empty imu0", "no IMU samples"),
             "no_imu": (None, "missing IMU folder")}
    for case, (imu, message) in cases.items():
        folder = tmp_path / case / "mav0"
        folder.mkdir(parents=True)
        if imu == "imu0":  # the first 2 s of the real IMU
            (folder / "imu0").mkdir()
            shutil.copy(src / "imu0" / "sensor.yaml", folder / "imu0")
            (folder / "imu0" / "data.csv").write_text("\n".join(imu_rows[:401]) + "\n")
        else:
            shutil.copytree(src / "state_groundtruth_estimate0",
                            folder / "state_groundtruth_estimate0")
        if imu == "empty imu0":  # the header row only
            (folder / "imu0").mkdir()
            shutil.copy(src / "imu0" / "sensor.yaml", folder / "imu0")
            (folder / "imu0" / "data.csv").write_text(imu_rows[0] + "\n")
        with pytest.raises(DataError, match=message) as err:
            simulate_hybrid(folder.parent, tmp_path / "out", SimConfig(frames=False),
                            duration=1.0, progress=False)
        assert str(err.value).startswith(str(folder.parent)) and "\n" not in str(err.value)
    with pytest.raises(DataError, match="runs past the end"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        simulate_hybrid(real.root, tmp_path / "out", SimConfig(frames=False), start=140.0,
                        duration=10.0, progress=False)
    assert not (tmp_path / "out").exists()


def test_cli_imu_from_writes_the_real_imu(real, tmp_path, capsys):
    from uavcal_jax.cli import main

    out = tmp_path / "cli"
    assert main(["simulate", "--imu-from", str(shared_path("euroc_v101_micro")), "--start", "1",
                 "--duration", "0.5", "--resolution", "64x40", "--no-depth", "--no-targets",
                 "--ideal-camera", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["imu"] == 101 and summary["imu_offset"] is None
    written = _read_quietly(out).imu
    first = np.searchsorted(real.imu.t_ns, written.t_ns[0])
    np.testing.assert_array_equal(written.gyro, real.imu.gyro[first:first + 101])
    assert main(["simulate", "--imu-from", str(out), "--trajectory", "x.txt", "--out",
                 str(tmp_path / "both")]) == 2
    assert "--imu-from" in capsys.readouterr().err
