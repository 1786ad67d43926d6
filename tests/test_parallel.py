"""over_devices: the batch split across host CPU devices gives the single-device numbers.

JAX fixes its CPU device count when it first runs, so the two-device check runs in a fresh
interpreter.
"""

import json
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.parallel import over_devices

SCRIPT = textwrap.dedent(
    """
    import json
    import jax, jax.numpy as jnp, numpy as np
    from uavcal_jax.parallel import use_cpu_devices, over_devices
    n = use_cpu_devices(2)
    jax.config.update("jax_enable_x64", True)
    from uavcal_jax.imu import preintegrate
    rng = np.random.default_rng(3)
    B, N = 5, 40  # 5 windows over 2 devices: one padded window
    dt = np.full((B, N), 0.005)
    gyro = rng.normal(0, 0.5, (B, N, 3))
    accel = rng.normal(0, 1.0, (B, N, 3)) + [0, 0, 9.81]
    bg = rng.normal(0, 0.01, (B, 3))
    fn = jax.vmap(lambda d, g, a, b: preintegrate(d, g, a, b))
    one = jax.jit(fn)(dt, gyro, accel, bg)
    split = over_devices(fn)(dt, gyro, accel, bg)
    diff = max(float(jnp.max(jnp.abs(jnp.asarray(x, float) - jnp.asarray(y, float))))
               for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(split)))
    shapes_equal = all(x.shape == y.shape
                       for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(split)))
    print(json.dumps({"devices": n, "diff": diff, "shapes_equal": shapes_equal,
                      "valid": bool(np.all(split.valid))}))
    """
)


def _run_fresh(script: str) -> dict:
    """Run ``script`` in a fresh interpreter; its last stdout line as JSON."""
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_two_devices_match_one():
    out = _run_fresh(SCRIPT)
    assert out["devices"] == 2
    assert out["shapes_equal"] and out["valid"]
    assert out["diff"] <= 1e-12, out


def test_one_device_is_plain_jit():
    f = over_devices(lambda x: jnp.cumsum(x, axis=1), devices=jax.devices()[:1])
    x = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(np.asarray(f(x)), np.cumsum(x, axis=1))


SHARD_SCRIPT = textwrap.dedent(
    """
    import json
    import jax, numpy as np
    from uavcal_jax.parallel import use_cpu_devices, over_devices, shard_batch
    n = use_cpu_devices(2)
    x = np.arange(24.0).reshape(6, 4)
    odd = np.arange(20.0).reshape(5, 4)
    placed, placed_odd = shard_batch((x, odd))
    f = over_devices(lambda a: a * 2.0 + 1.0)
    print(json.dumps({
        "devices": n,
        "split": sorted(d.id for d in placed.devices()),
        "shard_rows": sorted(s.data.shape[0] for s in placed.addressable_shards),
        "odd_whole": [s.data.shape[0] for s in placed_odd.addressable_shards],
        "from_one_device": bool(np.array_equal(
            np.asarray(f(jax.device_put(x, jax.devices()[0]))), x * 2.0 + 1.0)),
        "same": bool(np.array_equal(np.asarray(f(placed)), x * 2.0 + 1.0)
                     and np.array_equal(np.asarray(f(placed_odd)), odd * 2.0 + 1.0)),
    }))
    """
)


def test_shard_batch_places_halves_and_gives_the_same_result():
    out = _run_fresh(SHARD_SCRIPT)
    assert out["devices"] == 2
    assert out["split"] == [0, 1] and out["shard_rows"] == [3, 3]
    assert out["odd_whole"] == [5, 5]  # not a multiple of 2: whole on each, the call pads
    assert out["from_one_device"]  # inputs committed to one device are moved, not refused
    assert out["same"]
