"""The one config system: typed, frozen dataclass trees, ``key=value`` overrides, JSON in and
out.

Every run's settings are one tree of frozen dataclasses (a root per task: the calibrator run,
the VIO, the detector, the simulator). Defaults live in the dataclasses; presets are typed
instances of the root. This module only moves values in and out of such trees:

- :func:`apply_overrides`: ``["model.d_model=64", "window.size=160x96"]`` (the CLI's
  ``--set``) or a mapping of already-typed values, applied to a tree;
- :func:`to_dict` / :func:`from_dict`, :func:`write_config` / :func:`read_config`: the tree as
  JSON, written beside a run's results so that reading it back reproduces the run.

Parsing, type coercion and the unknown-key check are OmegaConf's structured configs (a
well-kept library made for dataclass trees; tyro was the other candidate, but it builds whole
argparse interfaces, not ``key=value`` lists). Two conveniences are added on top, for the
command line: a tuple field also takes ``32,32`` or ``160x96`` (OmegaConf wants ``[32,32]``),
and an optional field takes ``none``/``null``. The dataclasses' ``__post_init__`` validation
runs on the result.

Errors are :class:`ConfigError` (a :class:`~uavcal_jax.errors.DataError`, so the ``uavcal``
command prints one line and exits 2); an unknown key is :class:`UnknownConfigKey`, which names
the key and lists the valid ones.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from uavcal_jax.errors import DataError

__all__ = ["ConfigError", "UnknownConfigKey", "apply_overrides", "from_dict",
           "read_config", "to_dict", "valid_keys", "write_config"]

T = TypeVar("T")


class ConfigError(DataError):
    """A config value that does not parse or fails validation, or an override that is not
    ``key=value``."""


class UnknownConfigKey(ConfigError, KeyError):
    """A config key that the tree does not have (``args[0]`` names it and lists the valid
    keys; ``key`` is the full dotted key)."""

    def __init__(self, key: str, valid: Iterable[str]):
        self.key = key
        super().__init__(f"unknown config key {key!r}; valid keys: {', '.join(valid)}")

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _leaf_types(cls, prefix: str = "") -> dict[str, Any]:
    """``{"section.field": type hint}`` of every leaf of the dataclass tree ``cls``. An
    optional section (``Section | None``) is a key of its own (set to ``none``) besides its
    fields."""
    out: dict[str, Any] = {}
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        section = next((a for a in typing.get_args(hint) if dataclasses.is_dataclass(a)),
                       None) if _is_optional(hint) else None
        if dataclasses.is_dataclass(hint):
            out |= _leaf_types(hint, f"{prefix}{f.name}.")
        elif section is not None:
            out[prefix + f.name] = hint
            out |= _leaf_types(section, f"{prefix}{f.name}.")
        else:
            out[prefix + f.name] = hint
    return out


def valid_keys(config_or_cls) -> list[str]:
    """Every dotted leaf key of a config tree (instance or class), in field order."""
    cls = config_or_cls if isinstance(config_or_cls, type) else type(config_or_cls)
    return list(_leaf_types(cls))


def _is_optional(hint) -> bool:
    return (typing.get_origin(hint) in (typing.Union, types.UnionType)
            and type(None) in typing.get_args(hint))


def _is_tuple(hint) -> bool:
    if _is_optional(hint):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    return typing.get_origin(hint) is tuple or hint is tuple


def _command_line_value(text: str, hint) -> Any:
    """The CLI spellings OmegaConf does not know: ``none`` for an optional field, and a tuple
    as ``32,32`` or ``160x96``."""
    stripped = text.strip()
    if _is_optional(hint) and stripped.lower() in ("none", "null"):
        return None
    if _is_tuple(hint):
        inner = stripped[1:-1] if stripped.startswith("[") and stripped.endswith("]") else (
            stripped.replace("x", ","))
        return [p.strip() for p in inner.split(",") if p.strip()]
    return stripped


def _split(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise ConfigError(f"override {text!r} is not key=value")
    key, value = text.split("=", 1)
    return key.strip(), value


def _to_object(node, cls):
    try:
        obj = OmegaConf.to_object(node)
    except ValueError as err:  # a dataclass's own validation
        raise ConfigError(f"{cls.__name__}: {err}") from None
    except OmegaConfBaseException as err:
        raise ConfigError(str(err).splitlines()[0]) from None
    return obj


def apply_overrides(config: T, overrides: Iterable[str] | Mapping[str, Any]) -> T:
    """``config`` with ``"section.field=value"`` overrides applied, in order.

    Values are parsed to the field's type (``none``/``null`` for optional fields; tuples as
    ``64,64``, ``64x64`` or ``[64,64]``). A mapping may give already-typed values.

    Raises:
        UnknownConfigKey: a key the tree does not have (the message lists the valid ones).
        ConfigError: an override that is not ``key=value``, a value that does not parse, or a
            result that fails the dataclasses' validation.
    """
    items = list(overrides.items()) if isinstance(overrides, Mapping) else [
        _split(s) for s in overrides]
    if not items:
        return config
    leaves = _leaf_types(type(config))
    node = OmegaConf.structured(config)
    for key, value in items:
        if key not in leaves:
            raise UnknownConfigKey(key, leaves)
        if isinstance(value, str):
            value = _command_line_value(value, leaves[key])
        elif isinstance(value, tuple):
            value = list(value)
        try:
            # a merge (a frozen dataclass's node is read-only; a merge makes a new one)
            for part in reversed(key.split(".")):
                value = {part: value}
            node = OmegaConf.merge(node, value)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{key}: {str(err).splitlines()[0]}") from None
    return _to_object(node, type(config))


def to_dict(config) -> dict:
    """A JSON-ready dict of a config tree (tuples stay tuples; ``json`` writes them as
    lists)."""
    return dataclasses.asdict(config)


def from_dict(cls: type[T], data: Mapping) -> T:
    """Rebuild ``cls`` from :func:`to_dict` output (or its JSON); missing keys keep their
    defaults.

    Raises:
        UnknownConfigKey: a key ``cls`` does not have.  ConfigError: a bad value.
    """
    node = OmegaConf.structured(cls)
    try:
        node = OmegaConf.merge(node, OmegaConf.create(_jsonable(data)))
    except ConfigKeyError as err:
        raise UnknownConfigKey(str(err.full_key), valid_keys(cls)) from None
    except OmegaConfBaseException as err:
        raise ConfigError(str(err).splitlines()[0]) from None
    return _to_object(node, cls)


def _jsonable(data):
    if isinstance(data, Mapping):
        return {k: _jsonable(v) for k, v in data.items()}
    if isinstance(data, tuple | list):
        return [_jsonable(v) for v in data]
    return data


def write_config(path: str | Path, config, **extra) -> Path:
    """Write ``config`` (with any ``extra`` top-level entries, e.g. the command line) as
    indented JSON, atomically (a temporary file renamed into place). Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({**to_dict(config), **extra}, indent=2, default=_json_default)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as fh:
        fh.write(text + "\n")
    os.replace(tmp, path)
    return path


def _json_default(value):
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON")


def read_config(path: str | Path, cls: type[T], *, ignore: Iterable[str] = ()) -> T:
    """The ``cls`` tree written by :func:`write_config` at ``path`` (top-level keys in
    ``ignore``, such as ``extra`` entries, are skipped).

    Raises:
        DataError: a missing or unreadable file, or keys and values ``cls`` does not accept
            (the message names the file).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError("no such config file", path) from None
    except (OSError, ValueError) as err:
        raise DataError(f"not a JSON config ({err})", path) from None
    if not isinstance(data, dict):
        raise DataError("not a JSON object", path)
    skip = set(ignore)
    try:
        return from_dict(cls, {k: v for k, v in data.items() if k not in skip})
    except ConfigError as err:
        raise DataError(str(err), path) from None

