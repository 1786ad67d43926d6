"""The registry of IMU offset estimators, by name (``uavcal calib predict --method NAME``).

Each entry is an :class:`~uavcal_jax.pipeline.offset_estimate.OffsetMethod`: a ``configure``
that builds the method's options from ``--set``-style overrides (and the keyword arguments it
declares), and an ``estimate(sequence, options, *, progress)`` of a recording *without ground
truth* returning an :class:`~uavcal_jax.pipeline.offset_estimate.OffsetEstimate`. The
built-in ones are :data:`DEFAULT_METHOD` (``vio-bias``, the most accurate measured),
``visual-ls``, ``self-calib``, ``transformer`` and ``auto`` (those fused by their sigmas);
a new method is a small module here, beside
these, listed in :data:`METHODS` below (so that ``--help`` lists it) and given its options'
subtree in :class:`~uavcal_jax.pipeline.run_config.OffsetStageConfig`.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from uavcal_jax.errors import DataError
from uavcal_jax.pipeline import auto_offset, self_calib, transformer_offset, vio_bias, visual_ls
from uavcal_jax.pipeline.offset_estimate import OffsetEstimate, OffsetMethod

__all__ = ["DEFAULT_METHOD", "METHODS", "configure_method", "get_method", "method_names",
           "run_method"]

#: The methods by name, in ``--help`` order.
METHODS: dict[str, OffsetMethod] = {
    m.name: m for m in (vio_bias.METHOD, visual_ls.METHOD, self_calib.METHOD,
                        transformer_offset.METHOD, auto_offset.METHOD)}
#: The method used when none is named: measured the most accurate (the report of issue 20).
DEFAULT_METHOD = vio_bias.METHOD.name


def method_names() -> tuple[str, ...]:
    """The registered names, in registration order."""
    return tuple(METHODS)


def get_method(name: str) -> OffsetMethod:
    """The method ``name``.

    Raises:
        DataError: no such method (the message lists the registered ones).
    """
    try:
        return METHODS[name]
    except KeyError:
        raise DataError(f"unknown offset method {name!r}; methods: "
                        f"{', '.join(method_names())}") from None


def configure_method(name: str, overrides: Iterable[str] = (), **arguments: Any) -> Any:
    """The options of method ``name``: its ``configure`` with ``overrides`` and those of
    ``arguments`` that are not ``None``.

    Raises:
        DataError: an unknown method; an argument given (not ``None``) that the method does
            not take (the message names the methods that do); the method's own refusals.
    """
    method = get_method(name)
    given = {k: v for k, v in arguments.items() if v is not None}
    for key in given:
        if key not in method.arguments:
            takers = [m.name for m in METHODS.values() if key in m.arguments]
            raise DataError(f"method {name!r} takes no {key!r} (only "
                            f"{', '.join(takers) or 'no method'} does)")
    return method.configure(list(overrides), **given)


def run_method(name: str, sequence, options: Any, *, progress: bool = False) -> OffsetEstimate:
    """Method ``name``'s estimate of ``sequence`` (without ground truth) under ``options``
    (:func:`configure_method`)."""
    return get_method(name).estimate(sequence, options, progress=progress)
