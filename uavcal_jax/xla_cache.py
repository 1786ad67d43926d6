"""JAX's compiled functions across runs and within one: a persistent XLA compilation cache for
the command-line tools, so repeated invocations (train -> eval -> predict, or a resumed run)
reuse what an earlier one compiled, and :func:`release_if_crowded`, which drops the in-memory
ones before a long sweep of configurations exhausts the process's memory mappings."""

from __future__ import annotations

import gc
import os
from pathlib import Path

__all__ = ["enable_compilation_cache", "release_if_crowded"]


def enable_compilation_cache() -> None:
    """Point JAX's persistent compilation cache at ``UAVCAL_JAX_CACHE`` (default
    ``$XDG_CACHE_HOME/uavcal_jax/xla``, else ``~/.cache/uavcal_jax/xla``);
    ``UAVCAL_JAX_CACHE=off`` disables it. A cache directory set by the caller is kept."""
    import jax

    where = os.environ.get("UAVCAL_JAX_CACHE")
    if where == "off" or jax.config.jax_compilation_cache_dir:
        return
    if where is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"),
                                                                  ".cache")
        where = os.path.join(base, "uavcal_jax", "xla")
    try:
        os.makedirs(where, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    except Exception:  # noqa: BLE001 - a cache is an optimisation only, never a failure
        pass


def release_if_crowded() -> bool:
    """Drop JAX's compiled functions when this process's memory mappings pass half of
    ``vm.max_map_count``; returns whether it did (``False`` where ``/proc`` cannot tell).

    Every CPU executable holds LLVM-JIT mappings (a calibrator configuration's train, eval and
    init steps: about 2,000), so a few dozen configurations exhaust the default limit of
    65,530 and the next compile fails ("LLVM compilation error: Cannot allocate memory", then
    a crash). :func:`jax.clear_caches` frees them; the persistent compilation cache
    (:func:`enable_compilation_cache`) turns the recompile of a resumed fit into a load (its
    retrace remains).
    """
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps") as f:
            used = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if used <= limit // 2:
        return False
    import jax

    jax.clear_caches()
    gc.collect()
    return True
