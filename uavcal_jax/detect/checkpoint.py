"""Orbax checkpoints behind a small interface.

A :class:`Checkpoints` folder holds numbered steps, each with two items: ``state`` (any
pytree of arrays: the train state or just the model variables; orbax ``StandardSave``) and
``meta`` (a JSON dict: epoch, history, loader state, ...). Saves are atomic (orbax writes a
temporary folder and renames it) and old steps beyond ``max_to_keep`` are removed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp

from uavcal_jax.errors import DataError


class Checkpoints:
    """Numbered checkpoints of ``(state, meta)`` in ``directory``."""

    def __init__(self, directory: str | Path, max_to_keep: int | None = 1,
                 read_only: bool = False):
        self.directory = Path(directory).absolute()
        if read_only and not self.directory.is_dir():
            raise DataError("no checkpoints folder", self.directory)
        options = ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep, create=not read_only, read_only=read_only,
            enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options,
                                              item_names=("state", "meta"))

    def save(self, step: int, state: Any, meta: dict) -> None:
        """Write step ``step`` (replacing nothing: steps are unique) and wait for it."""
        self._manager.save(int(step), args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)), force=True)
        self._manager.wait_until_finished()

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def restore(self, abstract_state: Any, step: int | None = None) -> tuple[Any, dict]:
        """``(state, meta)`` of ``step`` (default the latest) into the structure of
        ``abstract_state`` (a pytree of arrays or ``jax.ShapeDtypeStruct``)."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise DataError("no checkpoint saved yet", self.directory)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
        out = self._manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()))
        return out["state"], dict(out["meta"])

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
