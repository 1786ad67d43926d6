"""Visual relative rotations from the front end's tracks (``uavcal_jax.vio.visual_rotation``),
their cache (``rotation_cache``) and the gyro bias they imply (``visual_gyro``), on a short
simulated flight against its ground truth."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from conftest import shared_path
from scipy.spatial.transform import Rotation, Slerp

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.imu import add_offset
from uavcal_jax.sim.config import IDEAL_IMU, SimConfig
from uavcal_jax.sim.simulate import simulate
from uavcal_jax.vio import rotation_cache as rc
from uavcal_jax.vio import visual_gyro as vg
from uavcal_jax.vio import visual_rotation as vr
from uavcal_jax.vio.initialize import gyro_bias_from_relative_rotations, gyro_bias_from_rotations


def true_relative_rotations(ground_truth, t0_ns: np.ndarray, t1_ns: np.ndarray
                            ) -> np.ndarray:
    """(K, 3, 3) ground-truth ``R_WB(t0)^T R_WB(t1)`` (slerp between the ground truth's
    samples): the reference the visual rotations are scored against."""
    t = np.asarray(ground_truth.t_ns, np.int64)
    t0_ns, t1_ns = np.asarray(t0_ns, np.int64), np.asarray(t1_ns, np.int64)
    if len(t0_ns) and (min(t0_ns.min(), t1_ns.min()) < t[0]
                       or max(t0_ns.max(), t1_ns.max()) > t[-1]):
        raise ValueError("frame times outside the ground truth's span")
    q = np.asarray(ground_truth.quaternion, np.float64)
    slerp = Slerp((t - t[0]) * 1e-9, Rotation.from_quat(q[:, [1, 2, 3, 0]]))
    R0 = slerp((t0_ns - t[0]) * 1e-9)
    R1 = slerp((t1_ns - t[0]) * 1e-9)
    return (R0.inv() * R1).as_matrix().reshape(-1, 3, 3)


OFFSET = np.array([0.03, -0.045, 0.02])  # rad/s, injected into the gyro
CONFIG = vg.VisualGyroConfig()


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """4 s of EuRoC V2_01 (turning while it flies) at 376x240 with EuRoC's IMU noise and
    biases; no motion blur (it halves the rendering time; the test is about the geometry)."""
    trajectory = shared_path("trajectories", "euroc", "V2_01_easy.txt")
    out = tmp_path_factory.mktemp("visual_rotation") / "rec"
    # an IMU with its data sheet's noise only: V1_01's vibration moves a 4 s mean by 1e-3
    # rad/s, twice this file's bound on the constant's recovery
    simulate(SimConfig(trajectory=str(trajectory), start=5.0, duration=4.0, seed=4,
                       resolution=(376, 240), blur_samples=1, depth=False, targets=False,
                       **IDEAL_IMU), out, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_euroc(out)


@pytest.fixture(scope="module")
def rotations(flight):
    return rc.cached_relative_rotations(flight, CONFIG.frontend, every=CONFIG.every)


def _angle_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(
        Rotation.from_matrix(np.swapaxes(A, -1, -2) @ B).as_rotvec(), axis=-1))


def _with_gyro_offset(seq, offset):
    gyro, accel = add_offset(seq.imu.gyro, seq.imu.accel, np.concatenate([offset, np.zeros(3)]))
    return dataclasses.replace(seq.imu, gyro=np.asarray(gyro, np.float64))


def _total_bias(seq, offset):
    return offset + seq.ground_truth.bias_gyro.mean(axis=0)


def test_visual_rotations_match_ground_truth(flight, rotations):
    assert rotations.valid.mean() >= 0.9
    truth = true_relative_rotations(flight.ground_truth, rotations.t0_ns, rotations.t1_ns)
    err = _angle_deg(rotations.R[rotations.valid], truth[rotations.valid])
    moved = _angle_deg(np.eye(3), truth[rotations.valid])
    assert np.median(moved) > 0.1  # the flight turns (median 0.23 deg per frame)
    assert np.median(err) < 0.1, np.median(err)  # measured: 0.019 deg (p90 0.052)
    # the convention: R maps body vectors at t1 to the body frame at t0 (not its inverse)
    assert np.median(_angle_deg(np.swapaxes(rotations.R, -1, -2)[rotations.valid],
                                truth[rotations.valid])) > np.median(moved)


def test_least_squares_recovers_an_injected_gyro_offset(flight, rotations):
    imu = _with_gyro_offset(flight, OFFSET)
    bg, fit = vg.gyro_bias_least_squares(imu, rotations)
    truth = _total_bias(flight, OFFSET)
    assert np.abs(bg - truth).max() < 0.002, (bg, truth)  # measured: 0.0009 rad/s
    # the stated covariance is of the right size: the error within 4 sigma per axis
    assert np.all(np.abs(bg - truth) < 4 * np.sqrt(np.diag(fit.cov)) + 1e-4)
    assert fit.used.sum() >= 0.8 * rotations.valid.sum()


def test_oracle_rotations_recover_the_offset_almost_exactly(flight, rotations):
    truth_R = true_relative_rotations(flight.ground_truth, rotations.t0_ns, rotations.t1_ns)
    oracle = rotations._replace(R=truth_R, valid=np.ones_like(rotations.valid))
    bg, fit = vg.gyro_bias_least_squares(_with_gyro_offset(flight, OFFSET), oracle)
    # measured 2.7e-4 rad/s: the zero-order hold of 200 Hz samples against the true rotation
    # (half a sample period times the mean angular acceleration) and the gyro's white noise;
    # 1e-4 over 40 s of the same flight
    assert np.abs(bg - _total_bias(flight, OFFSET)).max() < 5e-4
    assert fit.sigma < 1e-3


def test_cache_round_trips_and_is_reused(flight, rotations, monkeypatch):
    path = rc.cache_path(flight.root)
    assert path.is_file()

    def no_tracking(*args, **kwargs):
        raise AssertionError("recomputed despite the cache")

    monkeypatch.setattr(rc, "relative_rotations", no_tracking)
    again = rc.cached_relative_rotations(flight)
    for name in vr.VisualRotations._fields:
        np.testing.assert_array_equal(getattr(again, name), getattr(rotations, name))
    # the training's entry reads the folder's cache alone
    read = rc.read_cache(flight.root)
    np.testing.assert_array_equal(read.R, rotations.R)
    # another setting is another file (with the same name as before the modules' split: the
    # caches already written stay valid)
    assert rc.cache_path(flight.root, every=3) != path
    assert path.name == "visual_rotations.d8ac3704.npz"


def test_the_cache_works_from_the_sequence_given(flight, tmp_path):
    """A sequence without ground truth, in a folder holding nothing but the cache's output:
    the cache computes from the sequence's frames and never reads the folder."""
    copy = tmp_path / "empty"
    copy.mkdir()
    blind = dataclasses.replace(flight, ground_truth=None, root=copy)
    first = rc.cached_relative_rotations(blind)
    assert [p.name for p in copy.iterdir()] == [rc.cache_path(copy).name]
    np.testing.assert_array_equal(first.R, rc.cached_relative_rotations(flight).R)


def test_relative_form_generalises_the_keyframe_form():
    rng = np.random.default_rng(0)
    R_WB = Rotation.from_rotvec(rng.normal(0, 0.3, (6, 3))).as_matrix()
    dR = Rotation.from_rotvec(rng.normal(0, 0.1, (5, 3))).as_matrix()
    J = rng.normal(0, 0.05, (5, 3, 3))
    rel = np.swapaxes(R_WB[:-1], -1, -2) @ R_WB[1:]
    np.testing.assert_allclose(gyro_bias_from_relative_rotations(rel, dR, J),
                               gyro_bias_from_rotations(R_WB, dR, J), atol=1e-12)
    # zero weight drops an interval: the same as leaving it out
    w = np.array([1.0, 1.0, 0.0, 1.0, 1.0])
    keep = w > 0
    np.testing.assert_allclose(gyro_bias_from_relative_rotations(rel, dR, J, w),
                               gyro_bias_from_relative_rotations(rel[keep], dR[keep], J[keep]),
                               atol=1e-12)
