"""The benchmarks' one timing helper (``bench_*.py`` and ``detect_aerial.py``'s speed column).

A measurement compiles first, timed apart (:func:`time_compile`, or :func:`time_once` around a
first call that compiles), then makes ``warmup`` untimed calls and ``repeats``
timed ones (:func:`time_calls`). Every call is blocked on (``jax.block_until_ready`` of its
result, so asynchronous dispatch is not mistaken for speed) and timed in wall-clock and
process-CPU seconds. The figures are the median (robust to the bursts of a shared machine),
the minimum (the uncontended speed) and percentiles (:class:`Timings`); :func:`stats` gives the
mean, median and 95th percentile of times a program records itself (per frame, per stage).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

__all__ = ["Timings", "median", "stats", "time_calls", "time_compile", "time_once"]


def median(values) -> float:
    """The median of ``values`` as a float (the mean of the middle two for an even count)."""
    return float(np.median(np.asarray(values, np.float64)))


def stats(values) -> dict[str, float]:
    """``{"mean", "median", "p95"}`` of ``values`` (any unit; at least one value)."""
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "median": float(np.median(v)),
            "p95": float(np.percentile(v, 95))}


@dataclass(frozen=True)
class Timings:
    """``repeats`` timed calls, in call order.

    Attributes:
        wall_s: wall-clock seconds of each call.
        cpu_s: process CPU seconds of each call (all threads: above ``wall_s`` when the call
            runs on several cores).
        result: the last call's result (``None`` without timed calls).
    """

    wall_s: tuple[float, ...]
    cpu_s: tuple[float, ...]
    result: Any = None

    @property
    def median_s(self) -> float:
        return median(self.wall_s)

    @property
    def min_s(self) -> float:
        return float(min(self.wall_s))

    @property
    def mean_s(self) -> float:
        return float(np.mean(self.wall_s))

    @property
    def cpu_median_s(self) -> float:
        return median(self.cpu_s)

    def percentile_s(self, q: float) -> float:
        """The ``q``-th percentile (0-100) of the wall-clock seconds."""
        return float(np.percentile(self.wall_s, q))


def time_once(fn: Callable[[], Any]) -> tuple[Any, float]:
    """``(result, wall-clock seconds)`` of one call of ``fn()``, its result blocked on: a
    compile (``lambda: f.lower(*args).compile()``) or a first call that compiles."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t


def time_compile(jitted, *args) -> tuple[Any, float]:
    """``(compiled, seconds)``: ``jitted.lower(*args).compile()`` (tracing, lowering and XLA's
    compile), timed."""
    return time_once(lambda: jitted.lower(*args).compile())


def time_calls(fn: Callable[[], Any], *, repeats: int, warmup: int = 0) -> Timings:
    """Time ``repeats`` calls of ``fn()`` after ``warmup`` untimed ones; each call's result is
    blocked on inside its timed span (the CPU clock is read outside the wall-clock span)."""
    for _ in range(warmup):
        jax.block_until_ready(fn())
    wall, cpu, out = [], [], None
    for _ in range(repeats):
        c = time.process_time()
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return Timings(tuple(wall), tuple(cpu), out)
