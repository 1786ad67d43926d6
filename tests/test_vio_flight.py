"""The stereo VIO on a simulated flight that hovers before it flies (the first 12 s of EuRoC's
V1_02_medium trajectory: still for 3.8 s, then up to 1.5 m/s), as is and with 20 consecutive
black frames in the middle of the flight; against the simulator's ground truth."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_path
from vio_frames import frames_ate, process_frames

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.simulate import simulate
from uavcal_jax.vio import ate
from uavcal_jax.vio.run import run_vio, stereo_pairs

DURATION_S = 12.0
BLACK = range(170, 190)  # 8.5-9.5 s: the fastest second, up to 1.5 m/s


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    trajectory = shared_path("trajectories", "euroc", "V1_02_medium.txt")
    out = tmp_path_factory.mktemp("hover_then_fly") / "rec"
    simulate(SimConfig(trajectory=str(trajectory), duration=DURATION_S, seed=2, depth=False,
                       targets=False), out, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_euroc(out)


def _speed_at(seq, t_rel_s: float) -> float:
    gt = seq.ground_truth
    i = int(np.searchsorted(gt.t_ns, gt.t_ns[0] + t_rel_s * 1e9))
    return float(np.linalg.norm(gt.velocity[i]))


@pytest.mark.heavy
def test_hover_then_fly_runs_to_the_end_within_bounded_error(flight):
    # the flight is what the test says it is: still first, then fast
    assert _speed_at(flight, 2.0) < 0.05 and _speed_at(flight, 9.0) > 1.2
    result = run_vio(flight)
    traj = result.trajectory()
    assert len(traj) == len(stereo_pairs(flight))
    assert np.all(np.isfinite(traj.position)) and np.all(np.isfinite(traj.quaternion))
    assert result.resets == 0
    error = ate(traj, flight.ground_truth).translation
    assert error.rmse <= 0.02 and error.max <= 0.04  # measured: 5 and 10 mm
    flags = result.flags()
    assert np.all(flags["landmarks"][1:] > 20)


@pytest.mark.heavy  # 3 min on CI with its flight; resets and coasting: test_vio_failure
def test_twenty_black_frames_in_flight_coast_and_recover(flight):
    frames, _ = process_frames(flight, BLACK)
    assert all(f.has_pose and np.all(np.isfinite(f.position)) for f in frames)
    blind = frames[BLACK.start:BLACK.stop]
    assert [f.tracked for f in blind] == [0] * len(BLACK)
    # the window coasts on the IMU once the last landmarks have left it
    assert all(f.status in ("coasting", "reset") for f in blind[10:]), [f.status for f in blind]
    # tracking resumes once the images come back, and the estimate stays bounded
    after = frames[BLACK.stop + 10:]
    assert after and all(f.status == "tracking" and f.landmarks > 20 for f in after)
    error = frames_ate(frames, flight)
    assert error.rmse <= 0.03 and error.max <= 0.08  # measured: 8 and 21 mm
