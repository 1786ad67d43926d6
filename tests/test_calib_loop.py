"""The calibrator's training loop on a tiny simulated sequence: an interrupted and resumed run
ends at exactly the parameters (and metrics) of an uninterrupted one; the epoch order is a
function of (seed, epoch); the best checkpoint follows the monitored loss; a mismatched,
other-version or damaged checkpoint gives a one-line DataError naming the run folder, and a
half-written checkpoint (orbax's temporary folder) is never restored.

Tiny model (d 16, 1 layer, 2 heads, patch 16), 64x36 frames, 2 s windows at 4 Hz (8 frames),
batch 4: every fit in this module shares one compiled step (the configuration is the same).
"""

import json
import shutil

import jax
import numpy as np
import pytest

from uavcal_jax.calib.config import CalibConfig, LoopConfig
from uavcal_jax.calib.data import load_windows, split_windows
from uavcal_jax.calib.loop import epoch_order, fit, restore_run
from uavcal_jax.config import apply_overrides
from uavcal_jax.data.windows import WindowConfig
from uavcal_jax.errors import DataError
from uavcal_jax.runs import Checkpoints
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.simulate import simulate

TINY = ["model.d_model=16", "model.layers=1", "model.heads=2", "model.patch=16,16",
        "train.batch_size=4", "train.learning_rate=1e-3", "train.epochs=3"]
CONFIG = apply_overrides(CalibConfig(), TINY)
WINDOW = WindowConfig(duration=2.0, stride=1.0, size=(64, 36))


@pytest.fixture(scope="module")
def windows(tmp_path_factory):
    root = tmp_path_factory.mktemp("calib_loop") / "seq"
    simulate(SimConfig(duration=6, resolution=(64, 48), ideal_camera=True, camera_rate_hz=4,
                       depth=False, targets=False, seed=3), root, progress=False)
    parts = load_windows([root], WINDOW)
    ((train, val),) = split_windows(parts, 0.2, 0)
    return train, val


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def _rows(run_dir):
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if not k.endswith("time_s")} for r in rows]


@pytest.fixture(scope="module")
def full_run(windows, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("full")
    return run_dir, fit(CONFIG, *windows, run_dir, progress=False)


def test_resume_after_interruption_equals_uninterrupted(windows, full_run, tmp_path):
    run_dir, full = full_run
    assert full.summary["epochs"] == CONFIG.train.epochs
    # a kill after epoch 1's checkpoint, plus a half-written epoch 2 that must not restore
    part = fit(CONFIG, *windows, tmp_path, progress=False, stop_after=1)
    assert part.summary["epochs"] == 1
    junk = tmp_path / "checkpoints" / "last" / "2.orbax-checkpoint-tmp-1234"
    junk.mkdir()
    (junk / "garbage").write_text("half a checkpoint")
    with Checkpoints(tmp_path) as ck:
        assert ck.latest("last") == 1
    with (tmp_path / "metrics.jsonl").open("a") as f:  # a row written after the checkpoint
        f.write(json.dumps({"epoch": 2, "loss": -1.0}) + "\n")
    resumed = fit(CONFIG, *windows, tmp_path, progress=False, resume=True)
    assert resumed.summary["epochs"] == CONFIG.train.epochs
    for a, b in zip(_leaves(full.state), _leaves(resumed.state), strict=True):
        np.testing.assert_array_equal(a, b)
    assert _rows(tmp_path) == _rows(run_dir)
    # the parameters changed from their initialisation, and the saved last equals the final
    fresh = fit(CONFIG, *windows, tmp_path / "fresh", progress=False, stop_after=0)
    assert any(not np.array_equal(a, b) for a, b in zip(
        _leaves(fresh.state.params), _leaves(full.state.params), strict=True))
    last, _ = restore_run(run_dir, windows[0], kind="last")
    for a, b in zip(_leaves(last.params), _leaves(full.state.params), strict=True):
        np.testing.assert_array_equal(a, b)


def test_epoch_order_is_a_function_of_seed_and_epoch():
    key = jax.random.key(0)
    a, b = epoch_order(key, 3, 50), epoch_order(key, 3, 50)
    np.testing.assert_array_equal(a, b)
    assert sorted(a.tolist()) == list(range(50))
    assert not np.array_equal(a, epoch_order(key, 4, 50))
    assert not np.array_equal(a, epoch_order(jax.random.key(1), 3, 50))


def test_best_checkpoint_follows_the_monitored_loss(windows, tmp_path):
    res = fit(CONFIG, *windows, tmp_path, progress=False, loop=LoopConfig(monitor="val"))
    rows = _rows(tmp_path)
    assert res.summary["best_epoch"] == 1 + int(np.argmin([r["val_loss"] for r in rows]))
    with Checkpoints(tmp_path) as ck:
        assert ck.latest("best") == res.summary["best_epoch"]
    best, _ = restore_run(tmp_path, windows[1])
    from uavcal_jax.calib.loop import evaluate

    # the best checkpoint re-evaluated gives the validation loss recorded for its epoch
    again = evaluate(best, windows[1], 1, draws=LoopConfig().val_offsets)
    assert again["loss"] == pytest.approx(rows[res.summary["best_epoch"] - 1]["val_loss"],
                                          rel=1e-5)
    assert "offset_rmse" in again["baseline_mean_offset"]
    assert len(again["offsets"]) == LoopConfig().val_offsets


def _one_line_error(excinfo, *needles):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for n in needles:
        assert str(n) in msg, msg


def test_mismatched_config_or_version_or_damage_is_one_line(windows, full_run, tmp_path):
    run_dir, _ = full_run
    other = apply_overrides(CONFIG, ["model.d_model=32"])
    with pytest.raises(DataError) as e:
        fit(other, *windows, run_dir, progress=False, resume=True)
    _one_line_error(e, run_dir, "model.d_model", "16", "32")
    with pytest.raises(DataError) as e:  # an existing run is not silently overwritten
        fit(CONFIG, *windows, run_dir, progress=False)
    _one_line_error(e, run_dir, "resume")

    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    last = copy / "checkpoints" / "last" / str(CONFIG.train.epochs)
    meta_file = last / "meta" / "metadata"
    meta = json.loads(meta_file.read_text())
    meta_file.write_text(json.dumps({**meta, "format_version": 0}))
    with pytest.raises(DataError) as e:
        fit(CONFIG, *windows, copy, progress=False, resume=True)
    _one_line_error(e, copy, "format version 0")

    meta_file.write_text(json.dumps(meta))
    for f in (last / "state").rglob("*"):
        if f.is_file() and "manifest" not in f.name and f.parent.name == "d":
            f.write_bytes(b"\0" * 16)
    with pytest.raises(DataError) as e:
        fit(CONFIG, *windows, copy, progress=False, resume=True)
    _one_line_error(e, copy, "does not restore")


def test_validation_protocols_partition_the_windows(windows):
    from uavcal_jax.calib.data import Windows, kfold_windows, leave_one_out

    ws = windows[0][0].windows
    a = Windows(ws, np.arange(len(ws)), "a")
    b = Windows(ws, np.arange(len(ws)), "b")

    def ids(parts):
        return sorted((p.source, int(i)) for p in parts for i in p.indices)

    every = ids([a, b])
    ((train, val),) = split_windows([a, b], 0.2, 7)
    assert len(ids(val)) == round(0.2 * len(every))
    assert sorted(ids(train) + ids(val)) == every
    assert split_windows([a, b], 0.2, 7)[0][1][0].indices.tolist() == val[0].indices.tolist()
    folds = kfold_windows([a, b], 3)
    assert sorted(sum((ids(v) for _, v in folds), [])) == every
    for t, v in folds:
        assert not set(ids(t)) & set(ids(v)) and sorted(ids(t) + ids(v)) == every
        flat = [i + (len(ws) if s == "b" else 0) for s, i in ids(v)]
        assert flat == list(range(flat[0], flat[0] + len(flat)))  # one contiguous block
    loo = leave_one_out([a, b])
    assert [([p.source for p in t], [p.source for p in v]) for t, v in loo] == [
        (["b"], ["a"]), (["a"], ["b"])]
    with pytest.raises(DataError):
        leave_one_out([a])


def test_exported_weights_restore_as_trained_and_the_closed_form_export_zeroes_the_head(
        windows, full_run, tmp_path):
    """``export_weights``: the best checkpoint's parameters, restorable as a run; with
    ``closed_form_only`` the offset head's weights are zero (everything else as trained)."""
    from uavcal_jax.calib.loop import export_weights

    run_dir, _ = full_run
    train, _ = windows
    state, _ = restore_run(run_dir, train)
    plain, _ = restore_run(export_weights(run_dir, tmp_path / "plain", train), train)
    closed, _ = restore_run(export_weights(run_dir, tmp_path / "closed", train,
                                           closed_form_only=True), train)
    for a, b in zip(_leaves(state.params), _leaves(plain.params), strict=True):
        np.testing.assert_array_equal(a, b)
    head = closed.params["noise_predictor"]["head"]
    assert all(not np.any(np.asarray(v)) for v in jax.tree.leaves(head))
    assert np.any(np.asarray(state.params["noise_predictor"]["head"]["kernel"]))
    np.testing.assert_array_equal(np.asarray(closed.params["noise_predictor"]["query"]),
                                  np.asarray(state.params["noise_predictor"]["query"]))
