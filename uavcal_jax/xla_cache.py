"""A persistent XLA compilation cache for the command-line tools, so repeated invocations
(train -> eval -> predict, or a resumed run) reuse what an earlier one compiled."""

from __future__ import annotations

import os

__all__ = ["enable_compilation_cache"]


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
