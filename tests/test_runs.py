"""The training-run framework on a toy linear regression (pure SGD step, a few epochs):
an interrupted and resumed run equals the uninterrupted one (weights and metrics rows), the
best checkpoint is the epoch of the lowest validation loss and the last one the final state,
a half-written checkpoint is never picked up, a resume under another configuration and a
fresh run into a folder holding checkpoints are one-line errors, early stopping counts
patience, and a folder written by ``write_folder`` is whole or absent."""

import json
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.errors import DataError
from uavcal_jax.runs import (
    METRICS_FILE,
    Best,
    Checkpoints,
    Loop,
    RunSpec,
    Selection,
    read_metrics,
    train_epochs,
    write_folder,
)

RNG = np.random.default_rng(0)
X = RNG.normal(size=(40, 3)).astype(np.float32)
W_TRUE = np.float32([0.5, -1.0, 2.0])
Y = X @ W_TRUE + 0.1 * RNG.normal(size=40).astype(np.float32)
TRAIN, VAL = slice(0, 30), slice(30, 40)
BATCH = 8  # 30 samples: batches of 8, 8, 8, 6


@dataclass(frozen=True)
class Toy:
    lr: float = 0.05
    epochs: int = 5


@jax.jit
def _step(state, batch):
    x, y, lr = batch

    def loss(w):
        return jnp.mean((x @ w - y) ** 2)

    value, grad = jax.value_and_grad(loss)(state["w"])
    return {"w": state["w"] - lr * grad, "step": state["step"] + 1}, {"loss": value}


def _loop(cfg: Toy, patience: int | None = None, evaluate: bool = True) -> Loop:
    def batches(epoch: int):
        order = np.asarray(jax.random.permutation(jax.random.fold_in(jax.random.key(1), epoch),
                                                  30))
        for b in range(0, 30, BATCH):
            idx = order[b:b + BATCH]
            yield (X[TRAIN][idx], Y[TRAIN][idx], cfg.lr), idx.size

    def validate(state, _epoch):
        return {"val_loss": float(jnp.mean((X[VAL] @ state["w"] - Y[VAL]) ** 2))}

    return Loop(epochs=cfg.epochs, steps=4, batches=batches, step=_step,
                row=lambda state, means: {"loss": means["loss"]},
                evaluate=validate if evaluate else None,
                selection=Selection(lambda r: r.get("val_loss"), patience=patience),
                best=lambda state: {"w": state["w"]})


def _init():
    return {"w": jnp.zeros(3, jnp.float32), "step": jnp.zeros((), jnp.int32)}


def _fit(run_dir, cfg=Toy(), **kw):
    # nested tuples, as a config's anchors: the checkpoint's JSON holds lists
    spec = RunSpec(config=cfg, resolved={"lr": cfg.lr, "epochs": cfg.epochs,
                                         "sizes": ((1, 2), (3, 4))},
                   ignore=frozenset({"epochs"}))
    return train_epochs(run_dir, spec, _loop(cfg, kw.pop("patience", None),
                                             kw.pop("evaluate", True)),
                        _init, lambda: jax.eval_shape(_init), progress=False, **kw)


def _rows(run_dir):
    return [{k: v for k, v in r.items() if not k.endswith("time_s")}
            for r in read_metrics(run_dir)]


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("full")
    return run_dir, _fit(run_dir)


def test_best_and_last_checkpoints(full):
    run_dir, res = full
    rows = _rows(run_dir)
    assert [r["epoch"] for r in rows] == [1, 2, 3, 4, 5]
    assert rows[-1]["loss"] < rows[0]["loss"]  # it learns
    best_epoch = 1 + int(np.argmin([r["val_loss"] for r in rows]))
    assert res.best.epoch == best_epoch and res.best.score == rows[best_epoch - 1]["val_loss"]
    with Checkpoints(run_dir, read_only=True) as ck:
        assert ck.latest("best") == best_epoch and ck.latest("last") == 5
        last, meta = ck.restore("last", jax.eval_shape(_init))
        best, _ = ck.restore("best", {"w": jax.ShapeDtypeStruct((3,), jnp.float32)})
    np.testing.assert_array_equal(last["w"], res.state["w"])
    assert int(last["step"]) == 5 * 4 and meta["epoch"] == 5
    assert meta["early_stopping"]["best_epoch"] == best_epoch
    w = np.asarray(best["w"])  # the best weights re-score to their recorded loss
    assert float(np.mean((X[VAL] @ w - Y[VAL]) ** 2)) == pytest.approx(
        rows[best_epoch - 1]["val_loss"], rel=1e-6)
    assert json.loads((run_dir / "config.json").read_text()) == {"lr": 0.05, "epochs": 5}


def test_resume_equals_uninterrupted_and_skips_half_written(full, tmp_path):
    run_dir, res = full
    part = _fit(tmp_path, stop_after=2)
    assert len(part.history) == 2
    junk = tmp_path / "checkpoints" / "last" / "3.orbax-checkpoint-tmp-1234"
    junk.mkdir()
    (junk / "garbage").write_text("half a checkpoint")
    with (tmp_path / METRICS_FILE).open("a") as f:  # a row written after the checkpoint
        f.write(json.dumps({"epoch": 3, "loss": -1.0}) + "\n")
    with Checkpoints(tmp_path) as ck:
        assert ck.latest("last") == 2
    resumed = _fit(tmp_path, resume=True)
    np.testing.assert_array_equal(resumed.state["w"], res.state["w"])
    assert int(resumed.state["step"]) == int(res.state["step"])
    assert _rows(tmp_path) == _rows(run_dir) and resumed.best == res.best
    # the epoch budget may grow on resume: one more epoch, the same first five
    longer = _fit(tmp_path, Toy(epochs=6), resume=True)
    assert [r["epoch"] for r in longer.history] == [1, 2, 3, 4, 5, 6]


def test_config_mismatch_and_existing_run_are_one_line(full):
    run_dir, _ = full
    with pytest.raises(DataError) as e:
        _fit(run_dir, Toy(lr=0.1), resume=True)
    msg = str(e.value)
    assert "\n" not in msg and str(run_dir) in msg and "lr: 0.05 -> 0.1" in msg
    with pytest.raises(DataError, match="resume it or use another folder"):
        _fit(run_dir)


def test_early_stopping_and_unscored_runs(tmp_path):
    sel = Selection(lambda r: r["loss"], patience=3)
    best, stops = Best(), []
    for epoch, loss in enumerate([3.0, 2.0, 2.5, 2.1, 2.0, 1.0, float("nan")], start=1):
        best, stop = sel.update(best, loss, epoch)
        stops.append(stop)
    assert stops == [False, False, False, False, True, False, False]
    assert best == Best(1.0, 1, 6)  # a NaN is never an improvement
    high = Selection(lambda r: r["map"], maximize=True)
    assert high.update(Best(0.5, 0, 1), 0.6, 2)[0] == Best(0.6, 0, 2)
    assert high.update(Best(0.5, 0, 1), None, 2) == (Best(0.5, 0, 1), False)
    # patience 0 with a validation loss: stops after the first epoch that does not improve
    res = _fit(tmp_path / "early", Toy(lr=2.0), patience=0)
    assert res.stopped and len(res.history) < 5
    # nothing scored: the last epoch is kept as best
    res = _fit(tmp_path / "plain", evaluate=False)
    with Checkpoints(tmp_path / "plain", read_only=True) as ck:
        assert res.best.epoch == 5 and ck.latest("best") == 5


def test_write_folder_is_whole_or_absent(tmp_path):
    target = tmp_path / "export"
    write_folder(target, lambda d: (d / "a.txt").write_text("one"))

    def broken(d):
        (d / "a.txt").write_text("two")
        raise OSError("disk full")

    with pytest.raises(OSError):
        write_folder(target, broken)
    assert (target / "a.txt").read_text() == "one"
