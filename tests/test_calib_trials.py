"""The experiments' library parts: validation trials and their run folders
(``calib.trials``), the per-sensor metrics (``calib.metrics``), the budget scheduler
(``calib.schedule``) and the compiled-function releaser (``xla_cache``)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from uavcal_jax.calib import schedule
from uavcal_jax.calib.config import CalibConfig, LoopConfig
from uavcal_jax.calib.data import Windows
from uavcal_jax.calib.metrics import calibration_metrics, seed_summary, sensor_rmse
from uavcal_jax.calib.trials import (
    TRIAL_FORMAT,
    mean_std,
    mean_std_of,
    spread,
    trial_dir,
    trial_dirs,
    trial_sides,
    validation_windows,
    write_trial_data,
)
from uavcal_jax.config import apply_overrides
from uavcal_jax.errors import DataError
from uavcal_jax.xla_cache import release_if_crowded

SIX = ("gx", "gy", "gz", "ax", "ay", "az")


# ----------------------------------------------------------------------------- metrics


def test_sensor_rmse_by_hand():
    out = sensor_rmse([1.0, 2.0, 2.0, 0.0, 3.0, 4.0], SIX)
    assert out["gyro"] == pytest.approx(math.sqrt((1 + 4 + 4) / 3))
    assert out["accel"] == pytest.approx(math.sqrt((0 + 9 + 16) / 3))
    assert sensor_rmse([1.0, 2.0, 2.0], ("gx", "gy", "gz")) == {
        "gyro": pytest.approx(math.sqrt(3.0)), "accel": None}
    assert sensor_rmse([3.0, 4.0, 0.0], ("ax", "ay", "az"))["gyro"] is None


def test_sensor_rmse_pools_the_sensors_windows():
    rng = np.random.default_rng(0)
    pred, target = rng.normal(size=(7, 6)), rng.normal(size=(7, 6))
    m = calibration_metrics(pred, target)
    out = sensor_rmse(np.asarray(m["offset_rmse_per_channel"]), SIX)
    err = pred - target
    assert out["gyro"] == pytest.approx(np.sqrt(np.mean(err[:, :3] ** 2)), rel=1e-5)
    assert out["accel"] == pytest.approx(np.sqrt(np.mean(err[:, 3:] ** 2)), rel=1e-5)


def test_seed_summary_averages_seeds_by_hand():
    seeds = [{"sign_f1": 0.5, "offset_rmse": 2.0, "sign_f1_per_channel": [1, 0, 1, 0, 1, 0],
              "offset_rmse_per_channel": [1.0, 2.0, 2.0, 0.0, 3.0, 4.0]},
             {"sign_f1": 1.0, "offset_rmse": 1.0, "sign_f1_per_channel": [1] * 6,
              "offset_rmse_per_channel": [1.0, 1.0, 1.0, 2.0, 2.0, 2.0]}]
    out = seed_summary(seeds, SIX)
    assert out["sign_f1"] == pytest.approx(0.75) and out["offset_rmse"] == pytest.approx(1.5)
    assert out["sign_f1_per_channel"] == pytest.approx([1, 0.5, 1, 0.5, 1, 0.5])
    assert out["offset_rmse_per_channel"] == pytest.approx([1, 1.5, 1.5, 1, 2.5, 3])
    assert out["gyro_rmse"] == pytest.approx((math.sqrt(3.0) + 1.0) / 2)
    assert out["accel_rmse"] == pytest.approx((math.sqrt(25 / 3) + 2.0) / 2)
    gyro_only = seed_summary([{**seeds[1], "sign_f1_per_channel": [1] * 3,
                               "offset_rmse_per_channel": [1.0, 2.0, 2.0]}], SIX[:3])
    assert gyro_only["gyro_rmse"] == pytest.approx(math.sqrt(3.0))
    assert gyro_only["accel_rmse"] is None


# ----------------------------------------------------------------------------- trials


def test_mean_std_skips_missing_values():
    assert mean_std([1.0, None, 3.0, float("nan")]) == {"mean": 2.0, "std": 1.0,
                                                        "values": [1.0, 3.0]}
    assert mean_std([None]) is None
    rows = [{"a": 1.0, "b": None}, {"a": 2.0}]
    assert mean_std_of(rows, ("a", "b")) == {"a": {"mean": 1.5, "std": 0.5,
                                                   "values": [1.0, 2.0]}, "b": None}


def test_spread_keeps_first_and_last():
    assert spread(5, 3) == [0, 2, 4]
    assert spread(11, 3) == [0, 5, 10]
    assert spread(3, None) == [0, 1, 2] == spread(3, 7)


def test_trial_folders_and_data_json(tmp_path):
    assert trial_dir(tmp_path, 0, 1) == tmp_path
    assert trial_dir(tmp_path, 3, 5) == tmp_path / "trial_03" == tmp_path / TRIAL_FORMAT.format(3)
    ws = SimpleNamespace(name="seq")  # only carried through: validation_windows' cache hit
    train = [Windows(ws, np.array([0, 1, 2]), "/data/A")]
    val = [Windows(ws, np.array([4, 2]), "/data/B")]
    run = write_trial_data(trial_dir(tmp_path / "run", 1, 2), train, val)
    assert run == tmp_path / "run" / "trial_01"
    assert json.loads((run / "data.json").read_text()) == trial_sides(train, val) == {
        "train": [{"source": "/data/A", "indices": [0, 1, 2]}],
        "val": [{"source": "/data/B", "indices": [4, 2]}]}
    (back,) = validation_windows(run, None, {"/data/B": Windows(ws, np.arange(6), "/data/B")})
    assert back.source == "/data/B" and back.windows is ws
    np.testing.assert_array_equal(back.indices, [4, 2])
    with pytest.raises(DataError, match="trial_"):
        trial_dirs(tmp_path / "run")  # no config.json yet
    for i in (1, 0):
        (trial_dir(tmp_path / "run", i, 2) / "config.json").parent.mkdir(exist_ok=True)
        (trial_dir(tmp_path / "run", i, 2) / "config.json").write_text("{}")
    assert trial_dirs(tmp_path / "run") == [tmp_path / "run" / "trial_00", run]
    with pytest.raises(DataError, match="data.json"):
        validation_windows(tmp_path / "run" / "trial_00", None)


# ----------------------------------------------------------------------------- schedule


@pytest.fixture
def fake_fit(monkeypatch):
    """``schedule.fit`` as a counter of epochs per run folder: every call trains
    ``stop_after`` epochs, up to ``train.epochs``."""
    calls = []
    done: dict = {}

    def fit(config, train, val, run_dir, *, resume, progress, loop, stop_after):
        calls.append((run_dir.name, resume, stop_after))
        done[run_dir] = min(done.get(run_dir, 0) + stop_after, config.train.epochs)
        return SimpleNamespace(state=None, summary={
            "epochs": done[run_dir], "stopped_early": False, "best_epoch": done[run_dir],
            "best": {"loss": 1.0}})

    monkeypatch.setattr(schedule, "fit", fit)
    return calls


def _jobs(tmp_path, epochs):
    config = apply_overrides(CalibConfig(), {"train.epochs": epochs})
    return [schedule.Job(name, config, LoopConfig(), lambda: ([], []), tmp_path / name)
            for name in ("a", "b")]


def test_unlimited_budget_trains_each_job_to_its_epochs_in_one_call(tmp_path, fake_fit):
    firsts = []
    jobs = _jobs(tmp_path, 4)
    rec = schedule.train_jobs(jobs, schedule.Budget(None), quiet=True,
                              after_first=lambda job, res: firsts.append(job.name))
    assert fake_fit == [("a", False, 4), ("b", False, 4)] and firsts == ["a", "b"]
    assert rec["target_epochs"] is None and rec["epochs"] == {"a": 4, "b": 4}


def test_spent_budget_still_runs_two_epochs_per_job(tmp_path, fake_fit):
    budget = schedule.Budget(1e-6)
    jobs = _jobs(tmp_path, 10)
    rec = schedule.train_jobs(jobs, budget, quiet=True)
    assert fake_fit == [("a", False, 1), ("a", True, 1), ("b", False, 1), ("b", True, 1)]
    assert rec["target_epochs"] == 2 and rec["rounds"] == 0
    assert rec["epochs"] == {"a": 2, "b": 2} and all(j.calls == 2 for j in jobs)
    record = budget.record()
    assert record["budget_min"] == 1e-6 and record["over_budget_s"] >= 0.0
    assert schedule.Budget(None).record()["over_budget_s"] is None


def test_release_if_crowded_leaves_an_uncrowded_process_alone():
    assert release_if_crowded() is False


def test_bootstrap_interval_covers_the_mean_at_its_level():
    """Over 400 sets of 11 trials drawn from a normal distribution, the 95 % percentile
    interval holds the true mean in about 90-95 % of them (the percentile bootstrap is a
    little narrow for so few trials), and a set of one value is its own interval."""
    from uavcal_jax.calib.trials import bootstrap_interval

    rng = np.random.default_rng(0)
    hits = 0
    for k in range(400):
        stat = bootstrap_interval(rng.normal(1.0, 2.0, 11), resamples=2000, seed=k)
        hits += stat["low"] <= 1.0 <= stat["high"]
        assert stat["n"] == 11 and stat["low"] < stat["mean"] < stat["high"]
    assert 0.86 <= hits / 400 <= 0.97
    one = bootstrap_interval([0.5, None, float("nan")])
    assert one["mean"] == one["low"] == one["high"] == 0.5 and one["n"] == 1
    assert bootstrap_interval([None]) is None
