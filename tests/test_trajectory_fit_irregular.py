"""Trajectory files as they come: irregular intervals, near-duplicate stamps, gaps, mm noise.

A smooth analytic flight is sampled like a real motion-capture export (log-normal intervals
with a 20 ms median, 3 % of the poses doubled 0.03 ms later, gaps of 0.4, 0.8 and 1.2 s),
with 1 mm position noise and 1 mrad rotation noise per axis, and written as a TUM file. The
fit's noise-free IMU must match the analytic flight's within the simulator's IMU noise: the
EuRoC ADIS16448 white noise of one 200 Hz sample (``imu.noise.EUROC_ADIS16448``:
2.0e-3 m/s^2/sqrt(Hz) * sqrt(200 Hz) = 0.028 m/s^2, 1.70e-4 rad/s/sqrt(Hz) * sqrt(200 Hz)
= 0.0024 rad/s). The fit measures ~0.017 m/s^2 and ~0.0009 rad/s RMS (at most ~0.1 m/s^2,
inside the 1.2 s gap); before the fit handled
such files it gave ~200 m/s^2 (near-duplicate stamps made the jump remover shift the
flight by metres).
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.cli import main
from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.sim_config import read_sim_config
from uavcal_jax.data.tum import write_tum
from uavcal_jax.errors import DataError, FlightLimitWarning
from uavcal_jax.geometry.frames import GRAVITY
from uavcal_jax.imu.noise import EUROC_ADIS16448
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.imu_synth import synthesize_imu
from uavcal_jax.sim.pose_samples import remove_position_jumps, step_ramps
from uavcal_jax.sim.simulate import simulate_report
from uavcal_jax.sim.trajectory import Trajectory
from uavcal_jax.sim.trajectory_fit import (
    FitConfig,
    check_flight_limits,
    fit_trajectory_report,
    motion_peaks,
)

T0_NS = 1_700_000_000 * 10**9  # an absolute clock, like a real export's
DURATION = 16.0
GAPS = ((4.0, 0.4), (8.0, 0.8), (12.0, 1.2))  # (start s, length s)
POS_NOISE = 1e-3  # m per axis
ROT_NOISE = 1e-3  # rad per axis
#: one 200 Hz sample's white noise of the simulator's IMU model
ACCEL_WHITE = EUROC_ADIS16448.accel_noise_density * math.sqrt(200.0)
GYRO_WHITE = EUROC_ADIS16448.gyro_noise_density * math.sqrt(200.0)


def _analytic(s: np.ndarray, speedup: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Position (N, 3) and quaternion (N, 4, w x y z) of a smooth flight at ``s`` seconds
    (a few m/s^2, under 1 rad/s); ``speedup`` runs it that many times faster."""
    s = s * speedup
    p = np.stack([1.5 * np.sin(0.7 * s) + 0.3 * np.sin(2.1 * s + 1.0),
                  1.2 * np.cos(0.5 * s) + 0.2 * np.sin(1.7 * s),
                  1.5 + 0.4 * np.sin(0.9 * s)], axis=1)
    euler = np.stack([0.15 * np.sin(1.3 * s), 0.1 * np.sin(1.1 * s + 0.5),
                      0.8 * np.sin(0.4 * s) + 0.3 * s], axis=1)
    return p, Rotation.from_euler("xyz", euler).as_quat()[:, [3, 0, 1, 2]]


def _truth(speedup: float = 1.0) -> Trajectory:
    s = np.arange(int(DURATION * 200) + 1) / 200.0
    p, q = _analytic(s, speedup)
    return Trajectory.from_samples(T0_NS * 1e-9 + s, p, q, name="truth", t_ref_ns=T0_NS)


def _irregular_stamps(rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """int64 ns stamps like a motion-capture export's, and how many are near-duplicates."""
    dt = np.exp(rng.normal(math.log(0.02), 0.5, size=int(DURATION / 0.02 * 1.5)))
    s = np.concatenate([[0.0], np.cumsum(dt)])
    s = s[s <= DURATION]
    for start, length in GAPS:
        s = s[(s < start) | (s > start + length)]
    twins = s[(rng.random(len(s)) < 0.03) & (s < DURATION - 0.001)] + 3e-5
    return T0_NS + np.round(np.sort(np.concatenate([s, twins])) * 1e9).astype(np.int64), \
        len(twins)


def _noisy_recording(seed: int = 0, speedup: float = 1.0) -> tuple[GroundTruth, int]:
    rng = np.random.default_rng(seed)
    t_ns, twins = _irregular_stamps(rng)
    p, q = _analytic((t_ns - T0_NS) * 1e-9, speedup)
    p = p + rng.normal(scale=POS_NOISE, size=p.shape)
    turn = Rotation.from_rotvec(rng.normal(scale=ROT_NOISE, size=(len(t_ns), 3)))
    q = (Rotation.from_quat(q[:, [1, 2, 3, 0]]) * turn).as_quat()[:, [3, 0, 1, 2]]
    return GroundTruth(t_ns=t_ns, position=p, quaternion=q), twins


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(truth, path of the TUM file, its GroundTruth, near-duplicates, fit, report)."""
    gt, twins = _noisy_recording()
    path = write_tum(tmp_path_factory.mktemp("mocap") / "mocap.txt", gt)
    fit, report = fit_trajectory_report(path)
    return _truth(), path, gt, twins, fit, report


def _imu_error(fit: Trajectory, truth: Trajectory, t0: float, t1: float):
    """(gyro, accel) errors (N, 3) of the fit's noise-free IMU against the truth's, 200 Hz."""
    a = synthesize_imu(fit, rate_hz=200.0, t_start=t0, t_end=t1).imu
    b = synthesize_imu(truth, rate_hz=200.0, t_start=t0, t_end=t1).imu
    return a.gyro - b.gyro, a.accel - b.accel


def test_the_recording_is_as_irregular_as_a_real_export(recording):
    _, _, gt, twins, _, _ = recording
    dt = np.diff(gt.t_ns) * 1e-9
    assert dt.min() < 5e-5 and dt.max() > 1.1 and 0.015 < np.median(dt) < 0.025
    assert twins > 10


def test_irregular_noisy_file_gives_the_true_imu(recording):
    truth, _, _, _, fit, _ = recording
    d_gyro, d_accel = _imu_error(fit, truth, fit.t_start + 1.0, fit.t_end - 1.0)
    accel_rms, gyro_rms = np.sqrt(np.mean(d_accel**2)), np.sqrt(np.mean(d_gyro**2))
    print(f"accel RMS error {accel_rms:.4f} m/s^2 (max {np.abs(d_accel).max():.3f}), gyro "
          f"{gyro_rms:.5f} rad/s (max {np.abs(d_gyro).max():.4f})")
    # below one sample's white noise of the IMU model (0.028 m/s^2, 0.0024 rad/s)
    assert accel_rms < ACCEL_WHITE and gyro_rms < GYRO_WHITE
    # the worst errors are inside the gaps (next test)
    assert np.abs(d_accel).max() < 0.2 and np.abs(d_gyro).max() < 0.01


@pytest.mark.parametrize(("start", "length"), GAPS)
def test_gaps_are_bridged_smoothly(recording, start, length):
    """No data for up to 1.2 s: the penalty bridges the gap with the smoothest quintic, which
    stays within ~1 cm and ~0.1 m/s^2 of the true flight."""
    truth, _, _, _, fit, _ = recording
    t0 = T0_NS * 1e-9 + start
    d_gyro, d_accel = _imu_error(fit, truth, t0, t0 + length)
    t = np.linspace(t0, t0 + length, 50)
    assert np.abs(fit.position(t) - truth.position(t)).max() < 0.02
    assert np.abs(d_accel).max() < 0.2 and np.abs(d_gyro).max() < 0.01


def test_fit_report_measures_the_noise_and_the_flight(recording):
    truth, _, _, twins, fit, report = recording
    assert report.merged == twins and report.jumps == 0
    assert report.max_gap_s == pytest.approx(1.2, abs=0.1)
    assert report.median_period_s == pytest.approx(0.02, rel=0.1)
    # the noise the file was made with (3-D magnitudes: sqrt(3) per-axis sigma) ...
    assert report.position_noise_m == pytest.approx(math.sqrt(3) * POS_NOISE, rel=0.1)
    assert report.rotation_noise_rad == pytest.approx(math.sqrt(3) * ROT_NOISE, rel=0.1)
    # ... is what the fit leaves: it removed the noise, not the motion
    assert report.position_residual_rms_m == pytest.approx(report.position_noise_m, rel=0.05)
    assert report.rotation_residual_rms_rad == pytest.approx(report.rotation_noise_rad,
                                                             rel=0.05)
    assert report.smoothing_position > 10 * FitConfig().smoothing
    peaks = motion_peaks(truth, np.linspace(fit.t_start, fit.t_end, 3201))
    for key, value in peaks.items():
        assert getattr(report, key) == pytest.approx(value, rel=0.05), key
    assert 9.81 < report.peak_specific_force_mps2 < 2 * GRAVITY  # a gentle flight
    with warnings.catch_warnings():
        warnings.simplefilter("error", FlightLimitWarning)
        check_flight_limits(report)


def test_jump_removal_ignores_near_duplicate_stamps(recording):
    """Two noisy poses 0.03 ms apart are a velocity of ~50 m/s: the residual's noise grows as
    much there, so no step is seen in the raw file; a real 5 cm step still is, and becomes a
    ramp: the file's positions are kept away from it."""
    _, _, gt, _, _, _ = recording
    t = (gt.t_ns - gt.t_ns[0]) * 1e-9
    fixed, jumps = remove_position_jumps(t, gt.position)
    assert jumps.size == 0 and np.array_equal(fixed, gt.position)
    i = int(np.searchsorted(t, 2.0))
    stepped = gt.position.copy()
    stepped[i + 1:] += [0.05, 0.0, 0.0]
    fixed, jumps = remove_position_jumps(t, stepped)
    assert i in jumps.tolist()
    ramp = step_ramps(t, [0.5 * (t[i] + t[i + 1])], [[0.05, 0.0, 0.0]])
    assert np.abs(fixed - (stepped - ramp)).max() < 0.005
    assert np.abs(ramp).max() == pytest.approx(0.025, abs=0.002)  # half the step, at the step
    assert np.array_equal(fixed[np.abs(t - t[i]) > 2.5], stepped[np.abs(t - t[i]) > 2.5])


def test_sim_config_records_the_fit(recording, tmp_path):
    _, path, _, twins, _, _ = recording
    config = SimConfig(trajectory=str(path), start=1.0, duration=2.0, frames=False,
                       imu_noise=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FlightLimitWarning)
        report = simulate_report(config, tmp_path / "rec", progress=False)
    record = read_sim_config(report.root)
    fit = record["flight"]["trajectory_fit"]
    assert fit["merged"] <= twins and fit["jumps"] == 0
    assert fit["position_residual_rms_m"] == pytest.approx(math.sqrt(3) * POS_NOISE, rel=0.2)
    assert fit["rotation_residual_rms_rad"] == pytest.approx(math.sqrt(3) * ROT_NOISE, rel=0.2)
    for key in ("position_noise_m", "rotation_noise_rad", "peak_acceleration_mps2",
                "peak_specific_force_mps2", "peak_angular_rate_radps", "max_gap_s"):
        assert isinstance(fit[key], float), key
    assert 0.0 < fit["peak_angular_rate_radps"] < 2.0


def _shaking(path) -> None:
    """A 10 cm (peak to peak) oscillation at 5 Hz, sampled at 200 Hz: 5 g, more than a drone
    flies, and smooth enough that no sample looks like a position step."""
    t = np.arange(0.0, 6.0, 0.005)
    x = 0.05 * np.sin(2 * np.pi * 5.0 * t)
    p = np.stack([x, np.zeros_like(x), np.ones_like(x)], axis=1)
    write_tum(path, GroundTruth(t_ns=T0_NS + np.round(t * 1e9).astype(np.int64), position=p,
                                quaternion=np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))))


def test_shaking_warns(tmp_path):
    path = tmp_path / "shaking.txt"
    _shaking(path)
    _, report = fit_trajectory_report(path)
    assert report.jumps == 0
    assert 4 * GRAVITY < report.peak_specific_force_mps2 < 50 * GRAVITY
    with pytest.warns(FlightLimitWarning, match="exceeds what a drone flies"):
        check_flight_limits(report, where=path)


def test_square_wave_is_taken_for_position_steps():
    """A 10 cm square wave with instantaneous edges is what glitchy ground truth looks like:
    the edges are removed as position steps (counted in the report), leaving a still flight."""
    t = np.arange(0.0, 6.0, 0.005)
    p = np.zeros((len(t), 3))
    p[:, 0] = np.where(np.sin(2 * np.pi * t) >= 0.0, 0.05, -0.05)
    gt = GroundTruth(t_ns=T0_NS + np.round(t * 1e9).astype(np.int64), position=p,
                     quaternion=np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1)))
    _, report = fit_trajectory_report(gt)
    assert report.jumps >= 11
    assert report.peak_specific_force_mps2 == pytest.approx(GRAVITY, abs=0.1)


def test_simulate_prints_the_warning_as_one_line(tmp_path, capsys):
    path = tmp_path / "shaking.txt"
    _shaking(path)
    code = main(["simulate", "--out", str(tmp_path / "rec"), "--trajectory", str(path),
                 "--start", "1", "--duration", "2", "--no-frames", "--json"])
    out, err = capsys.readouterr()
    assert code == 0
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning: ") and str(path) in lines[0]
    summary = json.loads(out.strip().splitlines()[-1])
    assert len(summary["warnings"]) == 1
    assert summary["trajectory_fit"]["peak_specific_force_mps2"] > 4 * GRAVITY


def test_a_flight_no_airframe_flies_is_refused(tmp_path, capsys):
    """The analytic flight with its clock running 20x fast (timestamps in the wrong unit):
    ~80 g; refused with one line and exit 2, and nothing written."""
    gt, _ = _noisy_recording(seed=1, speedup=20.0)
    path = write_tum(tmp_path / "fast.txt", gt)
    _, report = fit_trajectory_report(path)
    assert report.peak_specific_force_mps2 > 50 * GRAVITY
    with pytest.raises(DataError, match="not one a drone can fly"):
        check_flight_limits(report, where=path)
    code = main(["simulate", "--out", str(tmp_path / "rec"), "--trajectory", str(path),
                 "--duration", "2", "--no-frames"])
    _, err = capsys.readouterr()
    assert code == 2 and str(path) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "rec").exists()
