"""Continuous-time trajectories: derivatives, procedural flights, fits to real ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.tum import read_tum
from uavcal_jax.errors import DataError
from uavcal_jax.geometry.frames import GRAVITY
from uavcal_jax.sim.flights import FlightConfig, procedural_flight, straight_flight
from uavcal_jax.sim.pose_samples import RAMP_ACCELERATION, remove_position_jumps, step_ramps
from uavcal_jax.sim.trajectory import Trajectory, sign_continuous
from uavcal_jax.sim.trajectory_fit import FitConfig, fit_tum_trajectory


def _rotations(q: np.ndarray) -> Rotation:
    """scipy rotations of (N, 4) quaternions in the project's (w, x, y, z) order."""
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def _rotation_angle(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    return (_rotations(qa).inv() * _rotations(qb)).magnitude()


def _check_derivatives(traj: Trajectory, t: np.ndarray, h: float = 2.0**-14) -> None:
    """Central differences of position / velocity / quaternion against the analytic ones.

    ``t`` is rounded to multiples of the power-of-two step ``h`` so that ``t +- h`` are exact
    in float64 even at absolute times like 1.4e9 s (whose spacing is 2.4e-7 s).
    """
    t = np.round(t / h) * h
    for f, df, scale in ((traj.position, traj.velocity, 1.0),
                         (traj.velocity, traj.acceleration, 1.0)):
        fd = (f(t + h) - f(t - h)) / (2 * h)
        ref = df(t)
        tol = 1e-6 * scale * max(1.0, float(np.abs(ref).max()))
        np.testing.assert_allclose(fd, ref, atol=tol, rtol=0)
    # body rate from the relative rotation over [t - h, t + h] (scipy's log map)
    omega_fd = (_rotations(traj.quaternion(t - h)).inv()
                * _rotations(traj.quaternion(t + h))).as_rotvec() / (2 * h)
    np.testing.assert_allclose(omega_fd, traj.angular_velocity_body(t), atol=1e-6, rtol=0)
    # The rotation matrix agrees with the quaternion, and the world rate is R @ body rate.
    R = traj.rotation_matrix(t)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(traj.angular_velocity_world(t),
                               np.einsum("nij,nj->ni", R, traj.angular_velocity_body(t)),
                               atol=1e-12)


def test_procedural_derivatives_are_consistent():
    traj = procedural_flight(3, 30.0)
    t = np.linspace(traj.t_start + 0.01, traj.t_end - 0.01, 997)
    _check_derivatives(traj, t)


def test_fitted_derivatives_are_consistent():
    from conftest import shared_path

    path = shared_path("trajectories", "euroc", "V1_02_medium.txt")
    gt = read_tum(path)
    traj = fit_tum_trajectory(gt, start=gt.t[0] + 20.0, duration=15.0)
    t = np.linspace(traj.t_start + 0.01, traj.t_end - 0.01, 501)
    _check_derivatives(traj, t)


def test_procedural_is_deterministic_and_seeds_differ():
    a, b, c = procedural_flight(7, 20.0), procedural_flight(7, 20.0), procedural_flight(8, 20.0)
    t = a.times(50.0)
    np.testing.assert_array_equal(a.position(t), b.position(t))
    np.testing.assert_array_equal(a.quaternion(t), b.quaternion(t))
    assert np.abs(a.position(t) - c.position(t)).max() > 0.5


@pytest.mark.parametrize("seed", [0, 1, 2, 5])
def test_procedural_flight_is_a_realistic_quadrotor(seed):
    cfg = FlightConfig()
    traj = procedural_flight(seed, 60.0, cfg)
    assert traj.t_start == cfg.t0 and traj.t_end == pytest.approx(cfg.t0 + 60.0)
    t = traj.times(100.0)
    p, v, a = traj.position(t), traj.velocity(t), traj.acceleration(t)
    # Starts hovering at the configured point.
    np.testing.assert_allclose(p[0], cfg.start_position, atol=1e-9)
    assert np.abs(v[0]).max() < 1e-9 and np.abs(a[0]).max() < 1e-9
    # Speeds and accelerations within the limits (a B-spline's derivatives are averages of
    # the plan's, so the limits hold exactly), and the flight moves.
    speed_h = np.linalg.norm(v[:, :2], axis=1)
    assert speed_h.max() <= cfg.max_speed + 1e-9
    assert speed_h.max() > 0.5
    assert np.abs(v[:, 2]).max() <= cfg.max_vertical_speed + 1e-9
    assert np.linalg.norm(a[:, :2], axis=1).max() <= cfg.max_accel + 1e-6
    assert np.abs(a[:, 2]).max() <= cfg.max_vertical_accel + 1e-6
    # Stays in its box, and covers some of it.
    lo, hi = traj.bounds()
    half = np.asarray(cfg.area_half_size)
    start = np.asarray(cfg.start_position)
    assert np.all(lo[:2] >= start[:2] - half - 1e-6) and np.all(hi[:2] <= start[:2] + half + 1e-6)
    assert cfg.altitude_range[0] - 1e-6 <= lo[2] and hi[2] <= cfg.altitude_range[1] + 1e-6
    assert np.max(hi - lo) > 2.0
    # Quadrotor attitude: body z along the thrust a + g e_z.
    thrust = a + np.array([0.0, 0.0, GRAVITY])
    thrust /= np.linalg.norm(thrust, axis=1, keepdims=True)
    z_body = traj.rotation_matrix(t)[:, :, 2]
    assert np.degrees(np.arccos(np.clip(np.sum(thrust * z_body, 1), -1, 1))).max() < 0.01
    # Some yawing, some hovering.
    omega = traj.angular_velocity_body(t)
    assert np.abs(omega[:, 2]).max() > 0.2
    assert np.mean(np.linalg.norm(v, axis=1) < 0.05) > 0.02


def test_straight_flight():
    cfg = FlightConfig(start_position=(1.0, 2.0, 1.5))
    heading = math.radians(30.0)
    traj = straight_flight(25.0, speed=2.0, config=cfg, heading=heading)
    t = traj.times(200.0)
    p, v = traj.position(t), traj.velocity(t)
    direction = np.array([math.cos(heading), math.sin(heading), 0.0])
    np.testing.assert_allclose(p[0], cfg.start_position, atol=1e-9)
    np.testing.assert_allclose(p[-1], np.asarray(cfg.start_position) + 25.0 * direction,
                               atol=1e-9)
    # Along the line, at the cruise speed, at rest at both ends, facing the heading.
    off_line = (p - p[0]) - np.outer((p - p[0]) @ direction, direction)
    assert np.abs(off_line).max() < 1e-9
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() == pytest.approx(2.0, abs=1e-9)
    assert np.mean(np.abs(speed - 2.0) < 1e-6) > 0.3
    assert speed[0] < 1e-9 and speed[-1] < 1e-9
    assert np.linalg.norm(traj.acceleration(t), axis=1).max() <= cfg.max_accel + 1e-6
    x_body = traj.rotation_matrix(t)[:, :, 0]
    assert np.abs(x_body @ direction).min() > math.cos(math.radians(10.0))


def test_bounds_contain_the_path():
    traj = procedural_flight(4, 25.0)
    lo, hi = traj.bounds()
    p = traj.position(np.linspace(traj.t_start, traj.t_end, 10007))
    assert np.all(p >= lo - 1e-4) and np.all(p <= hi + 1e-4)
    np.testing.assert_allclose(lo, p.min(0), atol=1e-3)
    np.testing.assert_allclose(hi, p.max(0), atol=1e-3)


def test_time_range_and_shapes():
    traj = procedural_flight(0, 10.0)
    assert traj.position(traj.t_start + 1.0).shape == (3,)
    assert traj.quaternion(np.zeros((2, 5)) + 1.0).shape == (2, 5, 4)
    assert traj.rotation_matrix(np.array([1.0, 2.0])).shape == (2, 3, 3)
    with pytest.raises(ValueError, match="outside the trajectory span"):
        traj.position(np.array([traj.t_end + 0.01]))
    with pytest.raises(ValueError, match="outside the trajectory span"):
        traj.angular_velocity_body(traj.t_start - 0.01)


def test_from_samples_constant_yaw_rate():
    w = 0.7
    t = np.linspace(0.0, 10.0, 1001)
    q = np.stack([np.cos(w * t / 2), 0 * t, 0 * t, np.sin(w * t / 2)], axis=1)
    traj = Trajectory.from_samples(t, np.zeros((len(t), 3)) + [1.0, 2.0, 3.0], q)
    tt = np.linspace(0.5, 9.5, 333)
    np.testing.assert_allclose(traj.angular_velocity_body(tt), np.tile([0, 0, w], (333, 1)),
                               atol=1e-8)
    assert _rotation_angle(traj.quaternion(tt), np.stack(
        [np.cos(w * tt / 2), 0 * tt, 0 * tt, np.sin(w * tt / 2)], 1)).max() < 1e-9


def test_sign_continuous():
    q = np.tile([[0.6, 0.0, 0.8, 0.0]], (6, 1)) * np.array([1, -1, -1, 1, -1, 1])[:, None]
    out = sign_continuous(q)
    assert np.all(np.sum(out[1:] * out[:-1], 1) > 0)
    np.testing.assert_allclose(out[0], q[0])


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["euroc/V1_01_easy.txt", "uzh_fpv/indoor_forward_7.txt"])
def test_fit_follows_real_ground_truth(name):
    from conftest import shared_path

    path = shared_path("trajectories", *name.split("/"))
    gt = read_tum(path)
    traj = fit_tum_trajectory(path)
    # The file's clock and span are kept.
    assert traj.t_start == pytest.approx(gt.t[0], abs=1e-9)
    assert traj.t_end == pytest.approx(gt.t[-1], abs=1e-6)
    state = traj.state_ns(gt.t_ns[:-1])
    dp = np.linalg.norm(state.position - gt.position[:-1], axis=1)
    ang = _rotation_angle(state.quaternion, gt.quaternion[:-1])
    # Smoothing removes mocap noise only: sub-millimetre / sub-0.1 degree RMS residuals.
    assert np.sqrt(np.mean(dp**2)) < 1e-3 and dp.max() < 0.01
    assert np.degrees(np.sqrt(np.mean(ang**2))) < 0.1 and np.degrees(ang.max()) < 1.0
    # The file path and the GroundTruth give the same fit.
    again = fit_tum_trajectory(gt)
    tt = np.linspace(traj.t_start, traj.t_end, 101)
    np.testing.assert_allclose(again.position(tt), traj.position(tt), atol=1e-12)


@pytest.mark.realdata
def test_fit_window_keeps_the_file_clock():
    from conftest import shared_path

    path = shared_path("trajectories", "euroc", "V1_01_easy.txt")
    gt = read_tum(path)
    start = gt.t[0] + 30.0
    win = fit_tum_trajectory(path, start=start, duration=20.0)
    assert win.t_start == pytest.approx(start) and win.t_end == pytest.approx(start + 20.0)
    full = fit_tum_trajectory(path)
    t = np.linspace(win.t_start, win.t_end, 401)
    # The window (fitted with edge padding) matches the full fit, ends included.
    assert np.abs(win.position(t) - full.position(t)).max() < 2e-3
    assert np.abs(win.acceleration(t) - full.acceleration(t)).max() < 0.5
    with pytest.raises(ValueError, match="outside"):
        win.position(start - 0.5)
    # Windows are clipped to the data; a window past the end is an error.
    tail = fit_tum_trajectory(path, start=gt.t[-1] - 5.0, duration=100.0)
    assert tail.t_end == pytest.approx(gt.t[-1])
    with pytest.raises(DataError):
        fit_tum_trajectory(path, start=gt.t[-1] + 1.0, duration=5.0)


def test_fit_needs_enough_poses():
    gt = GroundTruth(t_ns=np.arange(5, dtype=np.int64) * 5_000_000, position=np.zeros((5, 3)),
                     quaternion=np.tile([1.0, 0, 0, 0], (5, 1)))
    with pytest.raises(DataError, match="at least"):
        fit_tum_trajectory(gt)


def _synthetic_recording(seed: int = 0, rate: float = 200.0, duration: float = 30.0):
    traj = procedural_flight(seed, duration + 2.0)
    t_ns = (np.arange(int(duration * rate)) * (1e9 / rate)).astype(np.int64) + 500_000_000
    state = traj.state_ns(t_ns)
    return traj, t_ns, state


def test_fit_recovers_a_known_smooth_trajectory():
    """Sampled at 200 Hz with 0.2 mm / ~0.02 degree noise (random quaternion signs), the fit
    recovers the true motion. Its smoothing is matched to the noise it measures, so the
    accelerations keep a few hundredths of m/s^2 of it (the least-squares fit, without that,
    kept ~0.1 m/s^2 RMS, 0.4 max); the price is a bias of ~0.05 degree at the sharpest turns."""
    traj, t_ns, state = _synthetic_recording()
    rng = np.random.default_rng(0)
    q_noisy = state.quaternion + rng.normal(scale=2e-4, size=state.quaternion.shape)
    q_noisy /= np.linalg.norm(q_noisy, axis=1, keepdims=True)
    gt = GroundTruth(t_ns=t_ns, position=state.position + rng.normal(scale=2e-4,
                                                                       size=(len(t_ns), 3)),
                     quaternion=q_noisy * np.where(rng.random(len(t_ns)) < 0.3, -1, 1)[:, None])
    fit = fit_tum_trajectory(gt)
    t = np.linspace(fit.t_start + 1.0, fit.t_end - 1.0, 2000)
    assert np.abs(fit.position(t) - traj.position(t)).max() < 6e-4
    da = fit.acceleration(t) - traj.acceleration(t)
    assert np.abs(da).max() < 0.1 and np.sqrt(np.mean(da**2)) < 0.02
    assert np.degrees(_rotation_angle(fit.quaternion(t), traj.quaternion(t)).max()) < 0.07
    dw = fit.angular_velocity_body(t) - traj.angular_velocity_body(t)
    assert np.abs(dw).max() < 0.03 and np.sqrt(np.mean(dw**2)) < 0.004


def test_position_jumps_are_removed():
    """Step glitches (as in EuRoC's Machine Hall ground truth) do not reach the trajectory as
    acceleration spikes: each becomes a ramp of the same size whose acceleration stays under
    ``RAMP_ACCELERATION``, and the positions keep to the file's outside the ramps (shifting
    every later sample by the step, as the remover once did, left the 13 cm step's offset
    over the rest of the flight)."""
    traj, t_ns, state = _synthetic_recording(seed=1)
    pos = state.position.copy()
    jumps = {1000: [0.13, -0.05, 0.01], 3000: [-0.004, 0.002, 0.0], 4500: [0.0, 0.0, 0.02]}
    for i, d in jumps.items():
        pos[i:] += d
    pos[2000] += [0.01, 0.0, 0.0]  # a single outlier sample
    t = (t_ns - t_ns[0]) * 1e-9
    fixed, found = remove_position_jumps(t, pos)
    assert {999, 2999, 4499} <= set(found.tolist())
    # the outlier is moved onto its neighbours; the steps become ramps of their size
    assert np.abs(fixed[2000] - pos[2000] + [0.01, 0.0, 0.0]).max() < 1e-4
    ramps = np.zeros_like(pos)
    for i, d in jumps.items():
        ramps += step_ramps(t, [0.5 * (t[i - 1] + t[i])], [d])
    clean = pos - ramps
    clean[2000] -= [0.01, 0.0, 0.0]
    np.testing.assert_allclose(fixed, clean, atol=1e-4)
    # ... so away from them the file's positions are kept
    far = np.abs(t - t[2000]) > 0.1
    for i, d in jumps.items():  # a ramp's width: peak acceleration 5.77 |d| / width^2
        width = math.sqrt(10.0 / math.sqrt(3.0) * np.linalg.norm(d) / RAMP_ACCELERATION)
        far &= np.abs(t - t[i]) > 0.5 * width + 0.1
    assert np.count_nonzero(far) > len(t) // 2
    assert np.abs(fixed - pos)[far].max() < 1e-4
    gt = GroundTruth(t_ns=t_ns, position=pos, quaternion=state.quaternion)
    fit = fit_tum_trajectory(gt)
    tt = np.linspace(fit.t_start + 1.0, fit.t_end - 1.0, 5000)
    assert np.abs(fit.acceleration(tt) - traj.acceleration(tt)).max() < 0.05
    no_fix = fit_tum_trajectory(gt, config=FitConfig(jump_threshold=None))
    assert np.abs(no_fix.acceleration(tt) - traj.acceleration(tt)).max() > 10.0
    # Clean data is left alone.
    same, none = remove_position_jumps(t, state.position)
    assert none.size == 0 and np.abs(same - state.position).max() == 0.0


def test_fit_bridges_a_gap():
    """A 1.5 s hole in the poses (during motion) is bridged smoothly: the penalty keeps the
    solve well posed where no data constrain the knots."""
    traj, t_ns, state = _synthetic_recording(seed=2)
    speed = np.linalg.norm(state.velocity, axis=1)
    mid = int(np.argmax(speed[1000:-1000])) + 1000
    keep = np.ones(len(t_ns), bool)
    keep[mid - 150:mid + 150] = False
    gt = GroundTruth(t_ns=t_ns[keep], position=state.position[keep],
                     quaternion=state.quaternion[keep])
    fit = fit_tum_trajectory(gt)
    t = np.linspace(fit.t_start + 1.0, fit.t_end - 1.0, 3000)
    assert speed[mid] > 0.3
    assert np.abs(fit.position(t) - traj.position(t)).max() < 5e-3
    assert np.abs(fit.acceleration(t) - traj.acceleration(t)).max() < 0.1
    far = np.abs(t - t_ns[mid] * 1e-9) > 2.0
    assert np.abs(fit.position(t[far]) - traj.position(t[far])).max() < 1e-4


def test_quadrotor_attitude_balances_rotor_drag_and_a_tilted_thrust_axis():
    """What the accelerometer reads, ``R^T (a + g e_z)``: along body z alone for the ideal
    airframe; ``-d v_B`` on body x and y with rotor drag d (Faessler et al. 2018); the tilted
    thrust axis's direction times the thrust with a thrust tilt."""
    from uavcal_jax.geometry.frames import GRAVITY
    from uavcal_jax.sim.flights import quadrotor_attitude

    rng = np.random.default_rng(0)
    n = 50
    accel = rng.normal(0.0, 1.0, (n, 3))
    velocity = rng.normal(0.0, 2.0, (n, 3))
    yaw = rng.uniform(-np.pi, np.pi, n)
    need = accel + np.array([0.0, 0.0, GRAVITY])

    def reads(R):
        return np.einsum("nji,nj->ni", R, need)

    ideal = reads(quadrotor_attitude(accel, velocity, yaw))
    np.testing.assert_allclose(ideal[:, :2], 0.0, atol=1e-9)
    R = quadrotor_attitude(accel, velocity, yaw, rotor_drag=0.5)
    v_body = np.einsum("nji,nj->ni", R, velocity)
    np.testing.assert_allclose(reads(R)[:, :2], -0.5 * v_body[:, :2], atol=1e-9)
    tilted = reads(quadrotor_attitude(accel, velocity, yaw, thrust_tilt_deg=(1.0, -2.0)))
    axis = tilted / np.linalg.norm(tilted, axis=1, keepdims=True)
    want = Rotation.from_euler("xy", np.radians([1.0, -2.0])).as_matrix()[:, 2]
    np.testing.assert_allclose(axis, np.broadcast_to(want, axis.shape), atol=1e-9)
