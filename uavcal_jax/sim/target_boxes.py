"""Target labels of a rendered frame: the tight box around each target's visible pixels in
the object-id image of :func:`uavcal_jax.sim.render.render`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["target_boxes"]


def target_boxes(object_id: jax.Array, n_targets: int) -> tuple[jax.Array, jax.Array]:
    """Tight boxes around every target's visible pixels.

    Args:
        object_id: (H, W) int32 from :func:`render` (a leading batch dimension is allowed).
        n_targets: number of targets (static).

    Returns:
        boxes (n, 4) float32 ``x_min, y_min, x_max + 1, y_max + 1`` in pixels (zeros where
        nothing is visible) and visible pixel counts (n,) int32.
    """
    if object_id.ndim == 3:
        return jax.vmap(lambda o: target_boxes(o, n_targets))(object_id)
    H, W = object_id.shape
    if n_targets == 0:
        return jnp.zeros((0, 4), jnp.float32), jnp.zeros((0,), jnp.int32)
    ids = jnp.arange(n_targets, dtype=jnp.int32)
    mask = object_id[None, :, :] == ids[:, None, None]  # (n, H, W)
    rows = jnp.any(mask, axis=2)  # (n, H)
    cols = jnp.any(mask, axis=1)  # (n, W)
    count = jnp.sum(mask, axis=(1, 2), dtype=jnp.int32)
    y0 = jnp.argmax(rows, axis=1)
    y1 = H - jnp.argmax(rows[:, ::-1], axis=1)
    x0 = jnp.argmax(cols, axis=1)
    x1 = W - jnp.argmax(cols[:, ::-1], axis=1)
    boxes = jnp.stack([x0, y0, x1, y1], axis=1).astype(jnp.float32)
    boxes = jnp.where((count > 0)[:, None], boxes, 0.0)
    return boxes, count
