"""IMU preintegration on synthetic data: physics, vmap/mask, derivatives, covariance, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from imu_synthetic import true_delta, window

from uavcal_jax.errors import DataError
from uavcal_jax.geometry import so3
from uavcal_jax.imu import (
    THETA_LIMIT,
    ImuNoise,
    bias_correct,
    interval_batch,
    interval_samples,
    preintegrate,
)

SCHEMES = ["tangent", "manifold"]
BG = np.array([0.01, -0.02, 0.015])
BA = np.array([0.05, 0.02, -0.04])


def _rot_err(Ra, Rb):
    return float(np.linalg.norm(np.asarray(so3.log(np.asarray(Ra).T @ np.asarray(Rb)))))


def _leaves_close(a, b, rtol=1e-12, atol=1e-12):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_matches_true_motion(x64, scheme):
    dt, gyro, accel = window(0.2, 2.0, 2000)
    pim = preintegrate(dt, gyro + BG, accel + BA, BG, BA, scheme=scheme)
    dR, dv, dp = true_delta(0.2, 2.2)
    assert bool(pim.valid)
    assert abs(float(pim.delta_t) - 2.0) < 1e-12
    assert _rot_err(pim.delta_R, dR) < 2e-5
    np.testing.assert_allclose(np.asarray(pim.delta_v), dv, atol=3e-3)
    np.testing.assert_allclose(np.asarray(pim.delta_p), dp, atol=3e-3)
    np.testing.assert_allclose(np.asarray(so3.exp(pim.theta)), np.asarray(pim.delta_R), atol=1e-12)


def test_schemes_agree_to_first_order(x64):
    dt, gyro, accel = window(0.0, 1.0, 200)
    t = preintegrate(dt, gyro, accel, scheme="tangent")
    m = preintegrate(dt, gyro, accel, scheme="manifold")
    assert _rot_err(t.delta_R, m.delta_R) < 1e-3
    np.testing.assert_allclose(np.asarray(t.delta_v), np.asarray(m.delta_v), atol=1e-3)


def _random_windows(rng, n_windows=5, n_max=60):
    lengths = rng.integers(1, n_max + 1, n_windows)
    dts = np.zeros((n_windows, n_max))
    gyros = np.zeros((n_windows, n_max, 3))
    accels = np.zeros((n_windows, n_max, 3))
    mask = np.zeros((n_windows, n_max), bool)
    for i, n in enumerate(lengths):
        dts[i, :n] = rng.uniform(0.002, 0.008, n)
        gyros[i, :n] = rng.normal(scale=1.0, size=(n, 3))
        accels[i, :n] = rng.normal(scale=3.0, size=(n, 3)) + [0, 0, 9.81]
        mask[i, :n] = True
        # padding with finite garbage: must be ignored exactly
        dts[i, n:] = 0.37
        gyros[i, n:] = 5.0
        accels[i, n:] = -7.0
    return lengths, dts, gyros, accels, mask


@pytest.mark.parametrize("scheme, bias_covariance", [
    ("tangent", False),
    # 25-30 s each on CI: heavy
    pytest.param("manifold", False, marks=pytest.mark.heavy),
    pytest.param("tangent", True, marks=pytest.mark.heavy)])
def test_vmap_and_batch_equal_loop(x64, scheme, bias_covariance):
    rng = np.random.default_rng(0)
    lengths, dts, gyros, accels, mask = _random_windows(rng)
    bg = rng.normal(scale=0.01, size=(len(lengths), 3))
    ba = rng.normal(scale=0.05, size=(len(lengths), 3))
    kw = dict(scheme=scheme, bias_covariance=bias_covariance)
    vm = jax.jit(jax.vmap(lambda d, g, a, b1, b2, m: preintegrate(d, g, a, b1, b2, mask=m, **kw)))
    batched = vm(dts, gyros, accels, bg, ba, mask)
    native = preintegrate(dts, gyros, accels, bg, ba, mask=mask, **kw)
    _leaves_close(batched, native)
    for i, n in enumerate(lengths):
        single = preintegrate(dts[i], gyros[i], accels[i], bg[i], ba[i], mask=mask[i], **kw)
        one = jax.tree_util.tree_map(lambda x, i=i: x[i], batched)
        _leaves_close(one, single, rtol=1e-11, atol=1e-13)
        assert int(one.n_samples) == n
    # padding is skipped exactly: same numbers as the unpadded window
    n = lengths[0]
    unpadded = preintegrate(dts[0, :n], gyros[0, :n], accels[0, :n], bg[0], ba[0], **kw)
    _leaves_close(jax.tree_util.tree_map(lambda x: x[0], batched), unpadded, rtol=1e-11,
                  atol=1e-13)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_bias_jacobians_equal_jacfwd(x64, scheme):
    dt, gyro, accel = window(0.0, 1.0, 200, rate=2.0)
    b0 = jnp.concatenate([jnp.asarray(BG), jnp.asarray(BA)])
    pim = preintegrate(dt, gyro, accel, b0[:3], b0[3:], scheme=scheme)
    R0 = pim.delta_R

    @jax.jit
    @jax.jacfwd
    def jac(b):
        p = preintegrate(dt, gyro, accel, b[:3], b[3:], scheme=scheme)
        return so3.log(R0.T @ p.delta_R), p.theta, p.delta_v, p.delta_p

    jr, jt, jv, jp = (np.asarray(x) for x in jac(b0))
    tol = dict(atol=1e-9, rtol=0)
    np.testing.assert_allclose(jr[:, :3], pim.d_R_d_bg, **tol)
    np.testing.assert_allclose(jt[:, :3], pim.d_theta_d_bg, **tol)
    np.testing.assert_allclose(jv[:, :3], pim.d_v_d_bg, **tol)
    np.testing.assert_allclose(jp[:, :3], pim.d_p_d_bg, **tol)
    np.testing.assert_allclose(jr[:, 3:], np.zeros((3, 3)), **tol)
    np.testing.assert_allclose(jv[:, 3:], pim.d_v_d_ba, **tol)
    np.testing.assert_allclose(jp[:, 3:], pim.d_p_d_ba, **tol)
    J = np.asarray(pim.bias_jacobian)
    assert J.shape == (9, 6)
    np.testing.assert_allclose(J[3:6, 3:], pim.d_v_d_ba)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_bias_correction_is_first_order(x64, scheme):
    dt, gyro, accel = window(0.0, 1.0, 200)
    pim = preintegrate(dt, gyro, accel, BG, BA, scheme=scheme)
    d = 1e-3
    bg1, ba1 = BG + d * np.array([1.0, -0.5, 0.3]), BA + d * np.array([-2.0, 1.0, 0.5])
    ref = preintegrate(dt, gyro, accel, bg1, ba1, scheme=scheme)
    dR, dv, dp = bias_correct(pim, bg1, ba1)
    # second-order remainder: |d|^2 ~ 1e-5 times O(1) curvature
    assert _rot_err(dR, ref.delta_R) < 1e-6
    np.testing.assert_allclose(np.asarray(dv), np.asarray(ref.delta_v), atol=1e-5)
    np.testing.assert_allclose(np.asarray(dp), np.asarray(ref.delta_p), atol=1e-5)
    # and the correction is what closes the gap
    assert float(np.abs(np.asarray(pim.delta_v - ref.delta_v)).max()) > 1e-4
    # no new bias: no change
    dR0, dv0, _ = bias_correct(pim)
    np.testing.assert_allclose(np.asarray(dR0), np.asarray(pim.delta_R), atol=1e-15)
    np.testing.assert_allclose(np.asarray(dv0), np.asarray(pim.delta_v), atol=0)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_gradients_match_finite_differences(x64, scheme):
    rng = np.random.default_rng(3)
    dt, gyro, accel = window(0.0, 0.5, 200, rate=1.5)
    weights = {k: jnp.asarray(rng.normal(size=s)) for k, s in
               (("t", 3), ("v", 3), ("p", 3), ("c", (9, 9)), ("h", (3, 3)))}

    def loss(gyro, accel, bg, ba, offset):
        p = preintegrate(dt, gyro, accel, bg, ba, offset=offset, scheme=scheme)
        return (weights["t"] @ p.theta + weights["v"] @ p.delta_v + weights["p"] @ p.delta_p
                + 1e6 * jnp.sum(weights["c"] * p.cov) + jnp.sum(weights["h"] * p.d_v_d_bg))

    args = (jnp.asarray(gyro), jnp.asarray(accel), jnp.asarray(BG), jnp.asarray(BA),
            jnp.asarray([0.001, 0.002, -0.001, 0.01, -0.02, 0.03]))
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3, 4)))(*args)
    loss = jax.jit(loss)
    for i, g in enumerate(grads):
        assert np.all(np.isfinite(np.asarray(g)))
        direction = rng.normal(size=args[i].shape)
        eps = 1e-6
        plus = list(args)
        minus = list(args)
        plus[i] = args[i] + eps * direction
        minus[i] = args[i] - eps * direction
        fd = (float(loss(*plus)) - float(loss(*minus))) / (2 * eps)
        ad = float(jnp.sum(g * direction))
        assert abs(fd - ad) <= 1e-6 * max(1.0, abs(ad)), (i, fd, ad)


def test_offset_acts_like_a_bias(x64):
    dt, gyro, accel = window(0.0, 0.5, 200)
    off = np.array([0.01, -0.02, 0.03, 0.1, -0.2, 0.05])
    a = preintegrate(dt, gyro, accel, offset=off)
    b = preintegrate(dt, gyro, accel, off[:3], off[3:])
    for f in ("delta_R", "delta_v", "delta_p", "cov", "d_v_d_bg"):
        np.testing.assert_allclose(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), atol=1e-14)

    def f(o, which):
        p = preintegrate(dt, gyro, accel, offset=o)
        return jnp.sum(p.delta_v * jnp.array([1.0, 2.0, 3.0])) + jnp.sum(p.theta)

    g = jax.grad(f)(jnp.asarray(off), None)
    jb = preintegrate(dt, gyro, accel, off[:3], off[3:])
    # d/d(offset) = d/d(bias): minus the summed bias Jacobians
    expect_g = np.array([1.0, 2.0, 3.0]) @ np.asarray(jb.d_v_d_bg) + np.ones(3) @ np.asarray(
        jb.d_theta_d_bg)
    np.testing.assert_allclose(np.asarray(g[:3]), expect_g, atol=1e-10)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_closed_covariance_matches_recursive(x64, scheme):
    dt, gyro, accel = window(0.0, 1.0, 200, rate=2.0)
    noise = ImuNoise(integration_covariance=1e-8)
    c = preintegrate(dt, gyro, accel, noise=noise, scheme=scheme, covariance="closed").cov
    r = preintegrate(dt, gyro, accel, noise=noise, scheme=scheme, covariance="recursive").cov
    c, r = np.asarray(c), np.asarray(r)
    np.testing.assert_allclose(np.diag(c), np.diag(r), rtol=2e-4)
    scale = np.sqrt(np.outer(np.diag(r), np.diag(r)))
    assert np.max(np.abs(c - r) / scale) < 2e-4
    np.testing.assert_allclose(c, c.T, atol=0)
    assert np.all(np.linalg.eigvalsh(c) > 0)


def test_covariance_monte_carlo(x64):
    """The propagated covariance is the covariance of the preintegration error under white
    noise of the stated densities (tangent scheme, theta coordinates)."""
    dt, gyro, accel = window(0.0, 0.5, 100, rate=2.0)
    noise = ImuNoise(gyro_noise_density=2e-3, accel_noise_density=2e-2)
    ref = preintegrate(dt, gyro, accel, noise=noise)
    n_mc = 4000
    key_g, key_a = jax.random.split(jax.random.PRNGKey(0))
    sg = noise.gyro_noise_density / np.sqrt(dt[0])
    sa = noise.accel_noise_density / np.sqrt(dt[0])
    ng = jax.random.normal(key_g, (n_mc,) + gyro.shape) * sg
    na = jax.random.normal(key_a, (n_mc,) + accel.shape) * sa
    run = jax.jit(jax.vmap(lambda g, a: preintegrate(dt, g, a, noise=noise)))
    mc = run(gyro + ng, accel + na)
    err = np.concatenate([np.asarray(mc.theta - ref.theta), np.asarray(mc.delta_v - ref.delta_v),
                          np.asarray(mc.delta_p - ref.delta_p)], axis=1)
    emp = np.cov(err.T)
    cov = np.asarray(ref.cov)
    np.testing.assert_allclose(np.diag(emp), np.diag(cov), rtol=0.1)
    # correlations agree too
    corr_e = emp / np.sqrt(np.outer(np.diag(emp), np.diag(emp)))
    corr_c = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.max(np.abs(corr_e - corr_c)) < 0.06
    m2 = np.einsum("ni,ij,nj->n", err, np.linalg.inv(cov), err)
    assert abs(m2.mean() - 9.0) < 0.4


def test_bias_covariance_15(x64):
    dt, gyro, accel = window(0.0, 1.0, 200)
    noise = ImuNoise()
    p9 = preintegrate(dt, gyro, accel, noise=noise)
    p15 = preintegrate(dt, gyro, accel, noise=noise, bias_covariance=True)
    c = np.asarray(p15.cov)
    assert c.shape == (15, 15)
    np.testing.assert_allclose(c, c.T, atol=1e-18)
    assert np.all(np.linalg.eigvalsh(c) > -1e-18)
    np.testing.assert_allclose(np.diag(c)[9:12], noise.gyro_random_walk**2 * 1.0, rtol=1e-9)
    np.testing.assert_allclose(np.diag(c)[12:], noise.accel_random_walk**2 * 1.0, rtol=1e-9)
    np.testing.assert_allclose(c[9:, 9:], np.asarray(p15.cov_bias), rtol=1e-9, atol=1e-20)
    # bias drift inflates the delta covariance
    extra = c[:9, :9] - np.asarray(p9.cov)
    assert np.all(np.linalg.eigvalsh(extra) > -1e-12 * np.abs(np.asarray(p9.cov)).max())
    assert np.all(np.diag(extra) > 0)


def test_float32(x64):
    dt, gyro, accel = window(0.0, 1.0, 200)
    ref = preintegrate(dt, gyro, accel, BG, BA)
    with jax.enable_x64(False):
        p = preintegrate(np.float32(dt), np.float32(gyro), np.float32(accel), np.float32(BG),
                         np.float32(BA))
        assert p.delta_v.dtype == jnp.float32 and bool(p.valid)
        assert _rot_err(np.float64(p.delta_R), ref.delta_R) < 1e-5
        np.testing.assert_allclose(np.asarray(p.delta_v), np.asarray(ref.delta_v), atol=1e-4)
        np.testing.assert_allclose(np.asarray(p.delta_p), np.asarray(ref.delta_p), atol=1e-4)
        np.testing.assert_allclose(np.diag(p.cov), np.diag(ref.cov), rtol=1e-3)


# ---- bad input ----------------------------------------------------------------------------


def _good():
    return window(0.0, 0.1, 200)


@pytest.mark.parametrize(
    "corrupt, match",
    [
        (lambda d, g, a: (d, g.at[3, 1].set(jnp.nan), a), "sample 3: non-finite gyro/accel"),
        (lambda d, g, a: (d, g, a.at[5, 0].set(jnp.inf)), "sample 5: non-finite gyro/accel"),
        (lambda d, g, a: (d.at[2].set(0.0), g, a), "sample 2: dt <= 0"),
        (lambda d, g, a: (d.at[7].set(-0.01), g, a), "sample 7: dt <= 0"),
        (lambda d, g, a: (d.at[1].set(jnp.nan), g, a), "sample 1: non-finite dt"),
        (lambda d, g, a: (d[:0], g[:0], a[:0]), "empty interval"),
        (lambda d, g, a: (d, g[:, :2], a), "gyro must be"),
        (lambda d, g, a: (d[:-1], g, a), "dt must be"),
    ],
)
def test_bad_input_raises_eagerly(x64, corrupt, match):
    d, g, a = (jnp.asarray(x) for x in _good())
    d, g, a = corrupt(d, g, a)
    with pytest.raises(DataError, match=match):
        preintegrate(d, g, a)


def test_bad_bias_and_empty_mask_raise(x64):
    d, g, a = _good()
    with pytest.raises(DataError, match="bias"):
        preintegrate(d, g, a, np.array([np.nan, 0, 0]))
    with pytest.raises(DataError, match="empty"):
        preintegrate(d, g, a, mask=np.zeros(len(d), bool))
    with pytest.raises(ValueError, match="scheme"):
        preintegrate(d, g, a, scheme="rk4")


def test_bad_input_is_flagged_under_jit(x64):
    d, g, a = (jnp.asarray(x) for x in _good())
    f = jax.jit(lambda d, g, a, m: preintegrate(d, g, a, mask=m))
    m = jnp.ones(d.shape, bool)
    good = f(d, g, a, m)
    assert bool(good.valid)
    cases = [
        (d, g.at[3, 1].set(jnp.nan), a, m),
        (d.at[2].set(0.0), g, a, m),
        (d.at[2].set(-1.0), g, a, m),
        (d, g, a, jnp.zeros_like(m)),
    ]
    for args in cases:
        p = f(*args)
        assert not bool(p.valid)
        for leaf in jax.tree_util.tree_leaves(p):
            assert np.all(np.isfinite(np.asarray(leaf, float)))
    # a bad *masked* sample does not matter
    p = f(d, g.at[3, 1].set(jnp.nan), a, m.at[3].set(False))
    assert bool(p.valid) and int(p.n_samples) == len(d) - 1
    # per window under vmap
    gs = jnp.stack([g, g.at[0, 0].set(jnp.inf), g])
    pv = jax.vmap(lambda gg: preintegrate(d, gg, a))(gs)
    np.testing.assert_array_equal(np.asarray(pv.valid), [True, False, True])


def test_theta_limit_flag(x64):
    n = 200
    dt = np.full(n, 0.005)
    gyro = np.tile([0.0, 0.0, 7.0], (n, 1))  # 7 rad in 1 s > THETA_LIMIT
    accel = np.tile([0.0, 0.0, 9.81], (n, 1))
    assert THETA_LIMIT < 7.0
    assert not bool(preintegrate(dt, gyro, accel).valid)
    assert bool(preintegrate(dt, gyro, accel, scheme="manifold").valid)


# ---- intervals ------------------------------------------------------------------------------


def _stream(n=400, rate_hz=200, t0=1_403_715_273_262_142_976):
    rng = np.random.default_rng(5)
    t = t0 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    return t, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) + [0, 0, 9.81]


def test_interval_on_sample_times_is_the_plain_loop():
    t, g, a = _stream()
    iv = interval_samples(t, g, a, t[10], t[50])
    np.testing.assert_allclose(iv.dt, np.diff(t[10:51]) * 1e-9, rtol=0, atol=0)
    np.testing.assert_array_equal(iv.gyro, g[10:50])
    np.testing.assert_array_equal(iv.accel, a[10:50])


def test_interval_interpolates_at_the_start_and_cuts_at_the_end():
    t, g, a = _stream()
    ts = t[10] + 2_000_000  # 2 ms after sample 10 (of 5 ms)
    te = t[50] + 1_000_000
    iv = interval_samples(t, g, a, ts, te)
    assert abs(iv.dt.sum() - (te - ts) * 1e-9) < 1e-15
    assert iv.dt[0] == pytest.approx(3e-3, abs=1e-15)
    assert iv.dt[-1] == pytest.approx(1e-3, abs=1e-15)
    np.testing.assert_allclose(iv.gyro[0], g[10] + 0.4 * (g[11] - g[10]), atol=1e-15)
    np.testing.assert_array_equal(iv.gyro[1:], g[11:51])
    # inside one sample period
    iv2 = interval_samples(t, g, a, t[10] + 1_000_000, t[10] + 3_000_000)
    assert len(iv2.dt) == 1 and iv2.dt[0] == pytest.approx(2e-3, abs=1e-15)


def test_interval_errors():
    t, g, a = _stream()
    with pytest.raises(DataError, match="empty"):
        interval_samples(t, g, a, t[20], t[20])
    with pytest.raises(DataError, match="not inside"):
        interval_samples(t, g, a, t[0] - 1, t[20])
    with pytest.raises(DataError, match="not inside"):
        interval_samples(t, g, a, t[10], t[-1] + 1)
    with pytest.raises(DataError, match="increase"):
        interval_samples(t[::-1], g, a, t[20], t[10])
    g2 = g.copy()
    g2[15] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        interval_samples(t, g2, a, t[10], t[20])
    with pytest.raises(DataError, match="capacity"):
        interval_batch(t, g, a, [t[0]], [t[100]], capacity=10)


def test_interval_batch_preintegrates_as_each_interval(x64):
    t, g, a = _stream()
    starts = np.array([t[3] + 1_234_567, t[40], t[100] + 4_999_999])
    ends = np.array([t[43] + 10, t[41], t[300] + 1])
    batch = interval_batch(t, g, a, starts, ends)
    # preintegration of the batch equals per-interval preintegration
    pb = preintegrate(batch.dt, batch.gyro, batch.accel, mask=batch.mask)
    for i in range(len(starts)):
        iv = interval_samples(t, g, a, starts[i], ends[i])
        pi = preintegrate(iv.dt, iv.gyro, iv.accel)
        np.testing.assert_allclose(np.asarray(pb.delta_p[i]), np.asarray(pi.delta_p), atol=1e-13)
