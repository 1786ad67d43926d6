"""Spread a batched computation over the host's devices (e.g. the CPU cores).

XLA's CPU backend runs one program on one device and parallelises only large kernels inside
it; a scan over many small steps (preintegration, filters) therefore uses one core. With
several host devices (``jax.config.update("jax_num_cpu_devices", n)`` before JAX first
runs, or ``XLA_FLAGS=--xla_force_host_platform_device_count=n``), :func:`over_devices` splits
the leading (batch) axis of a computation across them with ``jax.shard_map``, and the
devices run concurrently. :func:`shard_batch` places inputs split the same way beforehand, so
that repeated calls on the same data do not first copy it from one device to the others.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["use_cpu_devices", "over_devices", "shard_batch"]


def use_cpu_devices(n: int) -> int:
    """Ask for ``n`` CPU devices; must run before JAX's first computation.

    Returns the number of CPU devices JAX then has (``1`` when it was already initialised
    with one device, e.g. because an array was created earlier in the process).
    """
    with contextlib.suppress(RuntimeError):  # backend already initialised: keep what it has
        jax.config.update("jax_num_cpu_devices", int(n))
    return len(jax.devices("cpu"))


def _batch_mesh(devices) -> Mesh:
    return Mesh(np.array(devices), ("batch",))


def shard_batch(tree, devices=None):
    """Every array leaf of ``tree`` (batched on axis 0) placed split across ``devices``
    (default: all devices of the default backend) as :func:`over_devices` splits it.

    Leaves whose batch size is not a multiple of the device count are copied whole to every
    device instead (the call pads them before splitting). :func:`over_devices` places its
    inputs this way on every call; placing them once beforehand makes that a no-op, so
    repeated calls on the same data do not copy each share off the first device again.
    """
    devices = list(jax.devices() if devices is None else devices)
    if len(devices) == 1:
        return jax.device_put(tree, devices[0])
    mesh = _batch_mesh(devices)
    split = NamedSharding(mesh, PartitionSpec("batch"))
    whole = NamedSharding(mesh, PartitionSpec())

    def place(x):
        x = jnp.asarray(x)
        even = x.ndim > 0 and x.shape[0] % len(devices) == 0
        return jax.device_put(x, split if even else whole)

    return jax.tree_util.tree_map(place, tree)


def over_devices(fn: Callable, devices=None) -> Callable:
    """``fn`` (every input and output batched on axis 0) run with the batch split across
    ``devices`` (default: all devices of the default backend).

    The batch is padded to a multiple of the device count by repeating its first element
    (so padding is valid data, never NaN) and the padding is removed from the outputs.
    Inputs are first placed with :func:`shard_batch` (wherever they were). With one device
    this is ``jax.jit(fn)``. The returned function has ``lower`` like a jitted one.
    """
    devices = list(jax.devices() if devices is None else devices)
    if len(devices) == 1:
        return jax.jit(fn)
    n = len(devices)
    mesh = _batch_mesh(devices)
    spec = PartitionSpec("batch")
    sharded = jax.shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec)

    @jax.jit
    def run(*args):
        size = jax.tree_util.tree_leaves(args)[0].shape[0]
        pad = -size % n

        def padded(x):
            return x if pad == 0 else jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)])

        out = sharded(*jax.tree_util.tree_map(padded, args))
        return jax.tree_util.tree_map(lambda x: x[:size], out)

    def call(*args):
        return run(*shard_batch(args, devices))

    call.lower = lambda *args: run.lower(*shard_batch(args, devices))
    return call
