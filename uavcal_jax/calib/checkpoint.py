"""Orbax checkpoints of a calibrator run: the last ``keep`` epochs and the best one.

A run folder ``RUN`` holds ``RUN/checkpoints/last/<epoch>`` (the newest ``keep`` epochs) and
``RUN/checkpoints/best/<epoch>`` (the epoch with the best monitored loss). Each step has two
items: ``state``, a pytree of arrays (``{"state": CalibState, "key": key_data}``, orbax
``StandardSave``), and ``meta``, a JSON dict (epoch, early-stopping record, data-order
position, the resolved configuration and :data:`FORMAT_VERSION`).

Atomicity: orbax writes a step into a temporary folder and renames it when complete; a run
killed mid-save leaves only the temporary folder, which :meth:`RunCheckpoints.latest` never
returns. Restoring checks the format version and the saved configuration against the wanted
one *before* reading arrays, so another config or version gives one line naming the run folder
and what differs (:class:`~uavcal_jax.errors.DataError`), not an orbax shape trace.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp
from absl import logging as absl_logging

from uavcal_jax.calib.config import run_layout
from uavcal_jax.errors import DataError

__all__ = ["FORMAT_VERSION", "KINDS", "RESUMABLE_KEYS", "RunCheckpoints", "config_differences"]

#: Version of the checkpoint layout (items, meta keys); bump on an incompatible change.
FORMAT_VERSION = 2
#: The two checkpoint series of a run.
KINDS = ("last", "best")
#: Configuration keys a restored checkpoint may differ in: the epoch budget (a resumed run
#: may train longer), the frame encoder's operand type (a numerics choice: the parameters
#: mean the same under either; checkpoints written before the field existed lack it) and the
#: frame-decoding threads (checkpoints written before the run config root lack them).
RESUMABLE_KEYS = frozenset({"train.epochs", "model.frame_encoder_dtype", "window.workers"})


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, Mapping):
        out: dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    if isinstance(tree, tuple):
        tree = list(tree)
    return {prefix[:-1]: tree}


def config_differences(saved: Mapping, wanted: Mapping,
                       ignore: frozenset[str] = RESUMABLE_KEYS,
                       defaults: Mapping | None = None) -> list[str]:
    """``"key: saved -> wanted"`` for every flattened key whose value differs (missing keys
    show as ``None``), except those in ``ignore``. A key ``saved`` lacks takes its value in
    ``defaults`` when given: a setting added after the checkpoint was written, whose default
    is the behaviour the checkpoint was trained with."""
    a, b = {**_flatten(defaults or {}), **_flatten(saved)}, _flatten(wanted)
    return [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b))
            if k not in ignore and a.get(k) != b.get(k)]


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}"


@contextlib.contextmanager
def _quiet_orbax(quiet: bool):
    if not quiet:
        yield
        return
    before = absl_logging.get_verbosity()
    absl_logging.set_verbosity(absl_logging.ERROR)
    try:
        yield
    finally:
        absl_logging.set_verbosity(before)


class RunCheckpoints:
    """The ``last`` and ``best`` checkpoint series of run folder ``run_dir``. Read-only, a
    folder may hold one series only (the shipped weights keep ``best``)."""

    def __init__(self, run_dir: str | Path, keep: int = 2, read_only: bool = False):
        self.run_dir = Path(run_dir).absolute()
        self._managers: dict[str, ocp.CheckpointManager] = {}
        for kind in KINDS:
            folder = self.run_dir / "checkpoints" / kind
            if read_only and not folder.is_dir():
                continue
            # read-only managers never delete, and orbax warns unless max_to_keep is None
            kept = None if read_only else (keep if kind == "last" else 1)
            with _quiet_orbax(read_only):  # orbax warns that read-only means read-only
                options = ocp.CheckpointManagerOptions(
                    max_to_keep=kept, create=not read_only, read_only=read_only,
                    enable_async_checkpointing=False)
                self._managers[kind] = ocp.CheckpointManager(folder, options=options,
                                                             item_names=("state", "meta"))
        if not self._managers:
            raise DataError("no checkpoints (not a calib run folder?)", self.run_dir)

    def _manager(self, kind: str) -> ocp.CheckpointManager:
        if kind not in self._managers:
            raise DataError(f"no {kind} checkpoints in this run folder", self.run_dir)
        return self._managers[kind]

    def save(self, kind: str, epoch: int, tree: Any, meta: dict) -> None:
        """Write epoch ``epoch`` of series ``kind`` (``meta`` gets the format version) and
        wait until it is renamed into place."""
        meta = {**meta, "format_version": FORMAT_VERSION}
        manager = self._manager(kind)
        manager.save(int(epoch), args=ocp.args.Composite(
            state=ocp.args.StandardSave(tree), meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()

    def latest(self, kind: str = "last") -> int | None:
        """The newest complete epoch of ``kind``, ``None`` when there is none."""
        return self._manager(kind).latest_step()

    def read_meta(self, kind: str = "last", epoch: int | None = None) -> tuple[int, dict]:
        """``(epoch, meta)`` of a saved step (default the newest)."""
        manager = self._manager(kind)
        epoch = manager.latest_step() if epoch is None else epoch
        if epoch is None:
            raise DataError(f"no {kind} checkpoint saved yet", self.run_dir)
        try:
            out = manager.restore(epoch, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except Exception as err:  # orbax raises many types for a damaged step
            raise DataError(f"{kind} checkpoint {epoch} is unreadable ({_first_line(err)})",
                            self.run_dir) from None
        return epoch, dict(out["meta"])

    def restore(self, kind: str, abstract_tree: Any, config: Mapping,
                epoch: int | None = None, ignore: frozenset[str] = RESUMABLE_KEYS,
                defaults: Mapping | None = None) -> tuple[Any, dict]:
        """``(tree, meta)`` of a saved step into the structure of ``abstract_tree`` (arrays
        or ``jax.ShapeDtypeStruct``), after checking that it was written with the format
        version and configuration ``config`` (a dict in the layout of
        :class:`~uavcal_jax.calib.config.CalibRunConfig`; saved configurations of the older
        layout are read too, :func:`~uavcal_jax.calib.config.run_layout`); the keys in
        ``ignore`` may differ; keys the saved configuration lacks take their value in
        ``defaults`` (:func:`config_differences`).

        Raises:
            DataError: no checkpoint, another format version, another configuration, or a
                damaged step; one line naming the run folder.
        """
        epoch, meta = self.read_meta(kind, epoch)
        version = meta.get("format_version")
        if version != FORMAT_VERSION:
            raise DataError(f"{kind} checkpoint {epoch} has format version {version}, this "
                            f"version reads {FORMAT_VERSION}", self.run_dir)
        diff = config_differences(run_layout(meta.get("config", {})), config, ignore, defaults)
        if diff:
            raise DataError(f"{kind} checkpoint {epoch} was written with another configuration "
                            f"({'; '.join(diff)})", self.run_dir)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_tree)
        try:
            out = self._manager(kind).restore(epoch, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract)))
        except Exception as err:
            raise DataError(f"{kind} checkpoint {epoch} does not restore "
                            f"({_first_line(err)})", self.run_dir) from None
        return out["state"], meta

    def close(self) -> None:
        for manager in self._managers.values():
            manager.close()

    def __enter__(self) -> RunCheckpoints:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
