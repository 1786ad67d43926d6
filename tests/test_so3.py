"""SO(3) helpers: against SciPy, finite differences and their defining identities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.geometry import so3
from uavcal_jax.imu import _ops


def _rotvecs(rng, n=64):
    """Random rotation vectors: tiny, small, moderate and near-pi angles."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, 1e-7, n // 4), rng.uniform(1e-4, 0.1, n // 4),
         rng.uniform(0.1, 2.5, n // 4), rng.uniform(2.5, np.pi - 1e-3, n - 3 * (n // 4))]
    )
    return axes * angles[:, None]


def test_hat_is_the_cross_product(x64):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(10, 3))
    W = so3.hat(v)
    u = rng.normal(size=(10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", W, u), np.cross(v, u), atol=1e-14)
    np.testing.assert_array_equal(W[:, [2, 0, 1], [1, 2, 0]], v)  # (W32, W13, W21)
    np.testing.assert_allclose(W, -np.swapaxes(W, 1, 2))


def test_exp_log_match_scipy(x64):
    rng = np.random.default_rng(1)
    phi = _rotvecs(rng)
    R = np.asarray(so3.exp(phi))
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(np.asarray(so3.log(R)), phi, atol=1e-9)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-14)


def test_quaternion_roundtrip(x64):
    rng = np.random.default_rng(2)
    R = Rotation.random(20, random_state=3)
    xyzw = R.as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    np.testing.assert_allclose(np.asarray(so3.from_quaternion(wxyz)), R.as_matrix(), atol=1e-14)
    q = np.asarray(so3.to_quaternion(R.as_matrix()))
    q_ref = np.where(wxyz[:, :1] < 0, -wxyz, wxyz)
    np.testing.assert_allclose(q, q_ref, atol=1e-12)
    del rng


def test_right_jacobian_definition(x64):
    """exp(phi + d) ~= exp(phi) exp(Jr(phi) d), checked by central differences."""
    rng = np.random.default_rng(4)
    for phi in _rotvecs(rng, 16):
        Jr = np.asarray(so3.right_jacobian(phi))
        R = np.asarray(so3.exp(phi))
        eps = 1e-6
        num = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            plus = np.asarray(so3.log(R.T @ np.asarray(so3.exp(phi + d))))
            minus = np.asarray(so3.log(R.T @ np.asarray(so3.exp(phi - d))))
            num[:, k] = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(Jr, num, atol=2e-8)
        Jinv = np.asarray(so3.right_jacobian_inv(phi))
        np.testing.assert_allclose(Jinv @ Jr, np.eye(3), atol=1e-12)


def test_right_jacobian_equals_autodiff(x64):
    """Jr(phi) = d log(exp(phi)^T exp(phi + d)) / d d at d = 0, by jax.jacfwd."""
    phi = jnp.array([0.3, -0.7, 1.1])

    def f(d):
        return so3.log(so3.exp(phi).T @ so3.exp(phi + d))

    np.testing.assert_allclose(jax.jacfwd(f)(jnp.zeros(3)), so3.right_jacobian(phi), atol=1e-12)


def test_series_coefficients_continuous_across_switch(x64):
    """The Taylor branch and the closed form agree at the switch-over point."""
    s_switch = so3.taylor_threshold(jnp.float64)
    below = jnp.asarray(s_switch * (1 - 1e-9))
    above = jnp.asarray(s_switch * (1 + 1e-9))
    names = ("a", "b", "c", "d", "db", "dc")
    for lo, hi, n in zip(so3.series_coefficients(below, names),
                         so3.series_coefficients(above, names), names, strict=True):
        assert abs(float(lo) - float(hi)) <= 1e-9 * abs(float(hi)), n


def test_kernel_coefficients_match_so3(x64):
    """The sin/cos-free coefficients of the preintegration kernel equal so3's."""
    s = jnp.concatenate([jnp.linspace(0, 0.02, 500), jnp.linspace(0.02, (1.8 * np.pi) ** 2, 2000)])
    ref = so3.series_coefficients(s, ("a", "b", "c", "d", "db", "dc"))
    got = _ops.coefficients(s)
    for r, g, tol in zip(ref, got, (1e-12, 1e-13, 1e-12, 1e-10, 1e-10, 1e-8), strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=tol, atol=1e-13)


def test_gradients_finite_at_identity(x64):
    for fn in (lambda v: jnp.sum(so3.exp(v)), lambda v: jnp.sum(so3.right_jacobian(v)),
               lambda v: jnp.sum(so3.right_jacobian_inv(v)),
               lambda v: jnp.sum(jnp.stack(_ops.coefficients(jnp.sum(v * v))))):
        g = jax.grad(fn)(jnp.zeros(3))
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("dtype", [jnp.float32])
def test_float32_exp_log(dtype):
    phi = jnp.asarray([[1e-4, 0.0, 0.0], [0.3, 0.2, -0.1], [1.0, -2.0, 0.5]], dtype)
    R = so3.exp(phi)
    assert R.dtype == dtype
    np.testing.assert_allclose(np.asarray(so3.log(R)), np.asarray(phi), atol=2e-6)
    np.testing.assert_allclose(
        np.asarray(so3.right_jacobian_inv(phi) @ so3.right_jacobian(phi)),
        np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-5)
