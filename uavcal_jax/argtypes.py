"""Command-line value types, options built from config fields, and JSON output shared by the
``uavcal`` commands and the experiment scripts (so neither imports the other).

:class:`ConfigFlag` / :func:`add_config_flags` / :func:`flag_overrides`: an option such as
``--imu-rate HZ`` is an alias of ``--set imu_rate_hz=HZ``: its default and its help come from
the config dataclass (the field's default and its line in the class docstring), so a field's
meaning and default live in one place; a command applies the given options, then ``--set``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import typing
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["ConfigFlag", "add_config_flags", "field_docs", "flag_overrides", "fraction",
           "parse_imgsz", "parse_offset", "parse_resolution", "parse_vector3", "positive",
           "positive_int", "print_json", "to_builtin"]


def parse_resolution(text: str) -> tuple[int, int]:
    """``"752x480"`` -> ``(752, 480)`` as ``(width, height)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT, e.g. 752x480, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"resolution must be at least 8x8, got {text!r}")
    return w, h


def parse_imgsz(text: str) -> tuple[int, int]:
    """``"640"`` -> (640, 640); ``"640x480"`` (width x height) -> (480, 640) as (H, W)."""
    try:
        parts = [int(v) for v in text.lower().replace(",", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected S or WxH, e.g. 640x480, got {text!r}") \
            from None
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected S or WxH, got {text!r}")
    w, h = parts
    if w % 32 or h % 32 or w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"image size must be multiples of 32, got {text!r}")
    return h, w


def _comma_floats(text: str, names: str, what: str) -> tuple[float, ...]:
    """``text`` as the finite floats named by ``names`` (``"X,Y,Z"``: 3 of them)."""
    n = names.count(",") + 1
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {n} comma-separated numbers {names}, got {text!r}") from None
    if len(values) != n:
        raise argparse.ArgumentTypeError(
            f"expected {n} comma-separated numbers {names}, got {len(values)} in {text!r}")
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"{what} values must be finite, got {text!r}")
    return values


def parse_offset(text: str) -> tuple[float, ...]:
    """``"GX,GY,GZ,AX,AY,AZ"`` -> an IMU offset, 6 finite floats (gyro rad/s xyz, accel m/s^2
    xyz, the order of :mod:`uavcal_jax.imu.offset`). A first value below zero needs the
    ``--option=-0.01,...`` form (argparse takes a lone ``-0.01,...`` for an option)."""
    return _comma_floats(text, "GX,GY,GZ,AX,AY,AZ", "offset")


def parse_vector3(text: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` -> 3 finite floats (``--option=-1,...`` when the first is negative)."""
    return _comma_floats(text, "X,Y,Z", "vector")  # type: ignore[return-value]


def positive(text: str) -> float:
    """A float > 0."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def positive_int(text: str) -> int:
    """An int >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def fraction(text: str) -> float:
    """A float in [0, 1]."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def to_builtin(value: Any) -> Any:
    """``json.dumps``'s ``default``: NumPy scalars and arrays, and paths, as built-ins."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__fspath__"):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def print_json(obj: Any) -> None:
    """Print ``obj`` as one JSON object on one line (numpy values converted)."""
    print(json.dumps(obj, default=to_builtin))


#: :attr:`ConfigFlag.const` when the option takes a value.
_UNSET: Any = object()


@dataclasses.dataclass(frozen=True)
class ConfigFlag:
    """One option that sets one field of a config tree (an alias of ``--set KEY=VALUE``).

    Attributes:
        key: the dotted field (``"imu_rate_hz"``, ``"train.epochs"``).
        flag: the option (``None``: ``--`` and the field's name with dashes; a boolean field
            that defaults to true gets ``--no-...``).
        type: parses the value (``None``: the field's type when it is int, float or str).
        metavar: the value's name in the help.
        choices: the values allowed.
        note: text added after the field's documentation (what the option adds to it).
        help: the whole help instead of the field's documentation (a field with none).
        default_text: how the help states the default (``None``: the field's value).
        const: when given, the option takes no value and sets the field to this one (e.g.
            ``--no-augment``: ``train.augment=None``).
    """

    key: str
    flag: str | None = None
    type: Callable[[str], Any] | None = None
    metavar: str | None = None
    choices: Sequence[Any] | None = None
    note: str = ""
    help: str | None = None
    default_text: str | None = None
    const: Any = _UNSET

    @property
    def dest(self) -> str:
        """The ``argparse`` attribute: the key with ``.`` as ``__``."""
        return self.key.replace(".", "__")


_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")


def _plain(text: str) -> str:
    """Docstring markup as plain text: ``:func:`~a.b.c``` -> ``c``, double backquotes
    dropped."""
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~")
                     else m.group(1), text)
    return " ".join(text.replace("``", "").split())


def field_docs(cls) -> dict[str, str]:
    """``{field: text}`` from the ``Attributes:`` section of ``cls``' docstring (Google
    style; ``a, b: text`` documents both), markup removed."""
    doc = cls.__doc__ or ""
    lines = doc.expandtabs().splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        return {}
    names = {f.name for f in dataclasses.fields(cls)}
    out: dict[str, str] = {}
    current: list[str] = []
    indent = None
    for line in lines[start + 1:]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if indent is None:
            indent = depth
        if depth < indent:
            break
        head, sep, rest = line.strip().partition(": ")
        keys = [k.strip() for k in head.split(",")]
        if depth == indent and sep and all(k in names for k in keys):
            current = keys
            for k in keys:
                out[k] = rest
        elif current:
            for k in current:
                out[k] += " " + line.strip()
    return {k: _plain(v) for k, v in out.items()}


def _field(config, key: str) -> tuple[Any, Any, str]:
    """``(type hint, default, doc)`` of the dotted ``key`` in the tree ``config`` (a
    dataclass instance, or a class whose defaults count)."""
    *path, name = key.split(".")
    node = config() if isinstance(config, type) else config
    for part in path:
        node = getattr(node, part)
    hint = typing.get_type_hints(type(node))[name]
    return hint, getattr(node, name), field_docs(type(node)).get(name, "")


def _shown(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return "{}x{}".format(*value)
    if isinstance(value, tuple):
        return ",".join(_shown(v) for v in value)
    return str(value)


def add_config_flags(parser, config, flags: Sequence[ConfigFlag]) -> None:
    """Add ``flags`` to ``parser`` (or an argument group) for the config tree ``config`` (a
    dataclass, whose defaults the help states, or an instance, whose values it states).

    An option left out is absent from the parsed namespace (the config keeps its value): so
    :func:`flag_overrides` gives only what the command line set. Each help is the field's
    docstring line (or :attr:`ConfigFlag.help`), the note, the ``--set`` key and the default.
    """
    for f in flags:
        hint, default, doc = _field(config, f.key)
        text = f.help if f.help is not None else doc
        text = " ".join(t for t in (text, f.note) if t).replace("%", "%%")
        kwargs: dict[str, Any] = {"dest": f.dest, "default": argparse.SUPPRESS}
        name = f.key.rsplit(".", 1)[-1].replace("_", "-")
        if f.const is not _UNSET:
            flag = f.flag or "--" + name
            kwargs.update(action="store_const", const=f.const,
                          help=f"{text} (--set {f.key}={_shown(f.const)})")
        elif hint is bool:
            flag = f.flag or "--" + ("no-" if default else "") + name
            kwargs["action"] = "store_false" if default else "store_true"
            kwargs["help"] = f"sets {f.key} to {str(not default).lower()}; {f.key}: {text}"
        else:
            flag = f.flag or "--" + name
            default_text = _shown(default) if f.default_text is None else f.default_text
            metavar = f.metavar or (None if f.choices else f.key.rsplit(".", 1)[-1].upper())
            kwargs.update(type=f.type or (hint if hint in (int, float, str) else None),
                          metavar=metavar,
                          choices=f.choices,
                          help=f"{text} (--set {f.key}) [default: {default_text}]")
        parser.add_argument(flag, **kwargs)


def flag_overrides(args: argparse.Namespace, flags: Sequence[ConfigFlag]) -> dict[str, Any]:
    """``{key: value}`` of the ``flags`` given on the command line, in ``flags``' order: typed
    overrides for :func:`uavcal_jax.config.apply_overrides`."""
    return {f.key: getattr(args, f.dest) for f in flags if hasattr(args, f.dest)}
