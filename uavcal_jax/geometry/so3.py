"""SO(3) helpers: hat, exponential and logarithm, right Jacobian and its inverse.

All functions are pure ``jax.numpy``, broadcast over leading axes (vectors ``(..., 3)``,
matrices ``(..., 3, 3)``), work in float32 and float64, and are differentiable everywhere
including at the identity (small angles use Taylor series behind the "double ``where``" so
that gradients stay finite).

Conventions (those of Forster et al., GTSAM and Sophus):

* ``exp(phi)`` is the rotation by ``|phi|`` about ``phi / |phi|``;
  ``exp(phi) = I + sin(t)/t W + (1 - cos(t))/t^2 W^2`` with ``W = hat(phi)``, ``t = |phi|``.
* The right Jacobian ``Jr(phi)`` satisfies ``exp(phi + d) ~= exp(phi) exp(Jr(phi) d)``:
  ``Jr = I - (1 - cos t)/t^2 W + (t - sin t)/t^3 W^2`` (GTSAM's ``dexp``).
* ``right_jacobian_inv(phi) = Jr(phi)^-1 = I + W/2 + (1/t^2 - (1 + cos t)/(2 t sin t)) W^2``,
  so that ``log(exp(phi) exp(d)) ~= phi + Jr^-1(phi) d``. It is singular at ``t = 2 pi``.

``exp`` and ``log`` go through :class:`jaxlie.SO3` (unit quaternions); the Jacobians are
closed forms written here, from the coefficient functions of :func:`series_coefficients`. Their
Taylor branch (:func:`taylor_threshold`, :func:`taylor_series`, :func:`horner`) is public for
the preintegration kernel, which computes the same coefficients without sin and cos.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie

__all__ = [
    "hat",
    "exp",
    "log",
    "right_jacobian",
    "right_jacobian_inv",
    "from_quaternion",
    "to_quaternion",
    "series_coefficients",
    "taylor_threshold",
    "taylor_series",
    "horner",
]


def hat(v: jnp.ndarray) -> jnp.ndarray:
    """Skew-symmetric ``(..., 3, 3)`` of ``v`` ``(..., 3)``: ``hat(v) @ u == cross(v, u)``."""
    v = jnp.asarray(v)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def exp(phi: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrix ``(..., 3, 3)`` of the rotation vector ``phi`` ``(..., 3)``."""
    phi = jnp.asarray(phi)
    return jaxlie.SO3.exp(phi).as_matrix()


def log(rotation: jnp.ndarray) -> jnp.ndarray:
    """Rotation vector ``(..., 3)`` (angle in ``[0, pi]``) of a rotation matrix ``(..., 3, 3)``."""
    rotation = jnp.asarray(rotation)
    return jaxlie.SO3.from_matrix(rotation).log()


def from_quaternion(wxyz: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrix of a (not necessarily normalised) quaternion ``(..., 4)`` in w, x, y, z."""
    q = jnp.asarray(wxyz)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jaxlie.SO3(wxyz=q).as_matrix()


def to_quaternion(rotation: jnp.ndarray) -> jnp.ndarray:
    """Unit quaternion ``(..., 4)``, w, x, y, z with ``w >= 0``, of a rotation matrix."""
    q = jaxlie.SO3.from_matrix(jnp.asarray(rotation)).wxyz
    return jnp.where(q[..., :1] < 0, -q, q)


# --------------------------------------------------------------------------------------
# Scalar coefficient functions of s = |phi|^2, with Taylor series near zero.
# --------------------------------------------------------------------------------------

# Taylor coefficients in s = theta^2 (five terms; the first omitted term is below 1e-19
# relative in float64 at the switch-over point and far below float32 precision in float32).
# Read them through taylor_series.
_TAYLOR = {
    # sin(t)/t
    "a": (1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0),
    # (1 - cos t)/t^2
    "b": (1.0 / 2.0, -1.0 / 24.0, 1.0 / 720.0, -1.0 / 40320.0, 1.0 / 3628800.0),
    # (t - sin t)/t^3
    "c": (1.0 / 6.0, -1.0 / 120.0, 1.0 / 5040.0, -1.0 / 362880.0, 1.0 / 39916800.0),
    # 1/t^2 - (1 + cos t)/(2 t sin t)
    "d": (1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0, 1.0 / 1209600.0, 1.0 / 47900160.0),
    # d b / d s
    "db": (-1.0 / 24.0, 2.0 / 720.0, -3.0 / 40320.0, 4.0 / 3628800.0, -5.0 / 479001600.0),
    # d c / d s
    "dc": (-1.0 / 120.0, 2.0 / 5040.0, -3.0 / 362880.0, 4.0 / 39916800.0, -5.0 / 6227020800.0),
}


def taylor_threshold(dtype) -> float:
    """The ``s = theta^2`` below which the coefficients use their Taylor series rather than the
    closed forms (which cancel catastrophically near 0): ``1e-2`` in float64, ``0.25`` in
    float32, where five terms are exact to the dtype's rounding."""
    return 1e-2 if jnp.dtype(dtype) == jnp.float64 else 0.25


def horner(coeffs, x):
    """``sum_k coeffs[k] x^k`` by Horner's rule (``coeffs`` lowest order first; ``x`` any
    array, the result has its shape)."""
    out = coeffs[-1]
    for c in coeffs[-2::-1]:
        out = out * x + c
    return out


def taylor_series(name: str, s: jnp.ndarray) -> jnp.ndarray:
    """The Taylor series in ``s = |phi|^2`` of the coefficient ``name`` (one of ``"a"``,
    ``"b"``, ``"c"``, ``"d"``, ``"db"``, ``"dc"``; see :func:`series_coefficients`), accurate
    for ``s <`` :func:`taylor_threshold`. Same shape as ``s``."""
    return horner(_TAYLOR[name], s)


def series_coefficients(s: jnp.ndarray, names=("a", "b", "c", "d")) -> tuple[jnp.ndarray, ...]:
    """Coefficients of ``s = |phi|^2`` used by exp and the Jacobians, safe at ``s = 0``.

    ``a = sin t / t``, ``b = (1 - cos t) / t^2``, ``c = (t - sin t) / t^3``,
    ``d = 1/t^2 - (1 + cos t) / (2 t sin t)``, and their ``s``-derivatives ``db``, ``dc``.
    Every value is differentiable in ``s`` (gradients finite at zero).
    """
    s = jnp.asarray(s)
    small = s < taylor_threshold(s.dtype)
    s_safe = jnp.where(small, jnp.ones_like(s), s)
    t = jnp.sqrt(s_safe)
    sin_t, cos_t = jnp.sin(t), jnp.cos(t)
    a = sin_t / t
    b = (1.0 - cos_t) / s_safe
    c = (1.0 - a) / s_safe
    exact = {
        "a": a,
        "b": b,
        "c": c,
        "d": (1.0 - 0.5 * a / b) / s_safe,
        "db": (0.5 * a - b) / s_safe,
        # dc/ds = ((a - cos t)/2 - c s) / s^2
        "dc": (0.5 * (a - cos_t) - c * s_safe) / (s_safe * s_safe),
    }
    return tuple(jnp.where(small, taylor_series(n, s), exact[n]) for n in names)


def _i_plus(phi: jnp.ndarray, alpha, beta) -> jnp.ndarray:
    """``I + alpha W + beta W^2``, ``W = hat(phi)``; ``alpha``, ``beta`` shaped ``phi[..., 0]``."""
    w = hat(phi)
    w2 = w @ w
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye + alpha[..., None, None] * w + beta[..., None, None] * w2


def right_jacobian(phi: jnp.ndarray) -> jnp.ndarray:
    """Right Jacobian ``Jr(phi)`` ``(..., 3, 3)``: ``exp(phi + d) ~= exp(phi) exp(Jr(phi) d)``."""
    phi = jnp.asarray(phi)
    _, b, c = series_coefficients(jnp.sum(phi * phi, axis=-1), ("a", "b", "c"))
    return _i_plus(phi, -b, c)


def right_jacobian_inv(phi: jnp.ndarray) -> jnp.ndarray:
    """Inverse right Jacobian ``Jr(phi)^-1`` ``(..., 3, 3)`` (singular at ``|phi| = 2 pi``)."""
    phi = jnp.asarray(phi)
    (d,) = series_coefficients(jnp.sum(phi * phi, axis=-1), ("d",))
    return _i_plus(phi, jnp.full_like(d, 0.5), d)
