"""The accelerometer bias from a trajectory (``uavcal_jax.imu.accel_alignment``).

On the demo's 12 s procedural flight (seed 9, 121 degrees of yaw; IMU only, no frames), with
a constant offset in the IMU and the simulator's own turn-on bias: the ground-truth poses at
20 Hz give back the whole constant accelerometer error (offset plus the ground truth's mean
bias); so do poses in a world frame tilted and shifted (the gauge a VIO's world frame has),
with their rotations wandering in tilt as a VIO's do (only the first of each segment is used)
and with millimetre position noise.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.true_offset import sensor_bias
from uavcal_jax.errors import DataError
from uavcal_jax.imu.accel_alignment import align_accel_bias, pick_nodes
from uavcal_jax.sim.config import IDEAL_IMU, SimConfig
from uavcal_jax.sim.simulate import simulate

OFFSET = (0.02, -0.015, -0.02, -0.08, -0.06, -0.1)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """``(sequence, poses at 20 Hz: t_ns, position, rotation, true (6,) constant error)``."""
    out = tmp_path_factory.mktemp("accel") / "flight"
    # an IMU with its data sheet's noise only: V1_01's vibration (1.4 m/s^2 RMS) and the
    # errors varying with the attitude move the answer by 0.015 m/s^2, over this file's bound
    simulate(SimConfig(duration=12.0, seed=9, frames=False, imu_offset=OFFSET,
                       **IDEAL_IMU), out, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = read_euroc(out)
    gt = seq.ground_truth
    every = slice(None, None, 10)  # 200 Hz -> 20 Hz
    rot = Rotation.from_quat(gt.quaternion[every][:, [1, 2, 3, 0]]).as_matrix()
    true = np.add(OFFSET, sensor_bias(gt))
    return seq, gt.t_ns[every], gt.position[every], rot, true


def _align(seq, t_ns, position, rotation, bias_gyro):
    return align_accel_bias(t_ns, position, rotation, seq.imu.t_ns, seq.imu.gyro,
                            seq.imu.accel, bias_gyro)


def test_true_poses_give_the_whole_constant_error(flight):
    seq, t_ns, p, rot, true = flight
    result = _align(seq, t_ns, p, rot, true[:3])
    error = result.bias_accel - true[3:]
    assert np.all(np.abs(error) < 0.01), error  # measured 4e-4, 3e-3, 1e-3 on the flight
    assert np.all(np.abs(true[3:]) > 0.09)  # a truth far from zero on every channel
    np.testing.assert_allclose(np.linalg.norm(result.gravity, axis=1), 9.81)
    assert result.segments == 1 and result.nodes.size >= 20
    assert np.all(result.bias_std < 0.01)


def test_a_tilted_world_wandering_rotations_and_noisy_positions(flight):
    seq, t_ns, p, rot, true = flight
    rng = np.random.default_rng(0)
    tilt = Rotation.from_euler("xy", [3.0, -2.0], degrees=True)
    position = tilt.apply(p) + [5.0, -2.0, 1.0] + rng.normal(0.0, 0.002, p.shape)
    # a VIO's tilt wanders by a degree with its bias estimate: 2 degrees off the true tilt
    # from a chain of gyro rotations would cost 0.3 m/s^2
    s = np.linspace(0.0, 1.0, len(t_ns))[:, None]
    wander = Rotation.from_rotvec(np.deg2rad(1.0) * np.hstack(
        [np.sin(7.0 * s), np.cos(5.0 * s), 0.0 * s]))
    rotation = (wander * tilt * Rotation.from_matrix(rot)).as_matrix()
    rotation[0] = (tilt * Rotation.from_matrix(rot[0])).as_matrix()
    result = _align(seq, t_ns, position, rotation, true[:3])
    error = result.bias_accel - true[3:]
    assert np.all(np.abs(error) < 0.03), error
    # the solved gravity is the tilted world's
    g = tilt.apply([0.0, 0.0, -9.81])
    assert np.degrees(np.arccos(result.gravity[0] @ g / 9.81 ** 2)) < 0.3


def test_nodes_split_at_gaps_and_after_the_segment_length():
    t = np.concatenate([np.arange(0.0, 6.0, 0.05), np.arange(8.0, 30.0, 0.05)])
    segments = pick_nodes(np.round(t * 1e9).astype(np.int64), 0.5, 10.0)
    starts = [t[s[0]] for s in segments]
    assert starts == pytest.approx([0.0, 8.0, 18.0])  # 28-30 s: 4 nodes, too few
    for s in segments:
        assert np.all(np.diff(t[s]) == pytest.approx(0.5))


def test_a_flight_too_short_is_refused(flight):
    seq, t_ns, p, rot, true = flight
    with pytest.raises(DataError, match="too short"):
        _align(seq, t_ns[:30], p[:30], rot[:30], true[:3])


def test_window_starts_recover_the_bias_and_move_with_an_injected_offset(flight):
    """The calibrator's metric start (``uavcal_jax.data.window_alignment``): 2 s windows whose
    alignment spans the flight around them give the whole constant error, with a response to
    a constant accelerometer offset near the identity (the data, not the prior, holds the
    bias); aligned over the 2 s window alone, the bias across gravity (IMU y and z) leans on
    the prior: its response is far below 1 and its sigma near the prior's."""
    from types import SimpleNamespace

    from uavcal_jax.data.window_alignment import PRIOR_STD, window_accel_starts

    seq, t_ns, p, rot, true = flight
    poses = SimpleNamespace(t_ns=t_ns, position=p, rotation=rot,
                            bias_gyro=np.tile(true[:3], (len(t_ns), 1)),
                            tracked=np.ones(len(t_ns), bool))
    imu = seq.imu
    starts = t_ns[0] + np.arange(0, 9) * 1_000_000_000
    two_s = 2_000_000_000
    whole = window_accel_starts(poses, imu.t_ns, imu.gyro, imu.accel, starts, two_s,
                                span_ns=12_000_000_000)
    assert np.all(np.abs(whole.start - true[3:]) < 0.02), whole.start - true[3:]
    np.testing.assert_allclose(whole.response, np.broadcast_to(np.eye(3), (9, 3, 3)),
                               atol=0.05)
    shifted = window_accel_starts(poses, imu.t_ns, imu.gyro, imu.accel + [0.05, -0.1, 0.2],
                                  starts[:2], two_s, span_ns=12_000_000_000)
    np.testing.assert_allclose(shifted.start,
                               whole.start[:2] + whole.response[:2] @ [0.05, -0.1, 0.2],
                               atol=2e-3)
    alone = window_accel_starts(poses, imu.t_ns, imu.gyro, imu.accel, starts, two_s)
    across = np.diagonal(alone.response, axis1=1, axis2=2)[:, 1:]
    assert np.median(across) < 0.5 and np.median(alone.std[:, 1:]) > 0.5 * PRIOR_STD
