"""Arithmetic of one preintegration step, shared by both covariance paths of the scan.

Per sample ``k`` (hold time ``h``, ``omega = gyro - b_g``, ``a = accel - b_a``) the scan
updates, exactly as GTSAM 4.3's ``TangentPreintegration::update`` (or, for the manifold
scheme, Forster's Euler recursion)::

    rotation:   theta += h Jr(theta)^-1 omega            (manifold: R <- R exp(omega h))
    velocity:   v += h Rn a ,  position: p += h v + h^2/2 Rn a
    H_rot_bg <- T H_rot_bg - h G
    H_v_bg   <- H_v_bg + V H_rot_bg ,  H_p_bg <- H_p_bg + h H_v_bg + h/2 V H_rot_bg
    H_v_ba   <- H_v_ba - h Rn ,        H_p_ba <- H_p_ba + h H_v_ba - h^2/2 Rn

with ``T`` the exact derivative of the rotation update with respect to the rotation state,
``V = -h Rn hat(a) Jr`` (tangent) or ``-h Rn hat(a)`` (manifold), ``G`` the derivative of the
rotation update with respect to ``omega`` (``Jr(theta)^-1`` / ``Jr(omega h)``), ``Rn`` the
rotation at the start of the step. These are exact derivatives of the mean recursion, so the
bias Jacobians equal ``jax.jacfwd`` of the means to rounding. :func:`rotation_step` computes
``(new rotation, T, V, G, Rn)``; :mod:`uavcal_jax.imu._closed` and
:mod:`uavcal_jax.imu._recursive` run the rest of the step and the covariance.

Two array layouts. Matrix helpers (:func:`mm`, :func:`mv`, :func:`mT`) take ``(..., 3, 3)``
and ``(..., 3)`` arrays with any leading batch axes; products are three broadcast
multiply-adds rather than ``dot`` calls, which XLA fuses into element-wise loops (much faster
on CPU than many tiny batched matrix multiplications). Component helpers (``c*``) take a vector
as a tuple of 3 arrays and a 3x3 matrix as a row-major tuple of 9 arrays, each of the batch
shape: every operation is then element-wise over the whole batch (contiguous, SIMD-vectorised
loops over the windows) instead of loops over tiny trailing axes, natively batched and under
``jax.vmap`` alike.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from uavcal_jax.geometry import so3

# ---- 3x3 helpers on (..., 3, 3) / (..., 3) arrays ----------------------------------------


def mm(x, y):
    """``x @ y`` as broadcast multiply-adds (no ``dot``)."""
    return (x[..., :, 0:1] * y[..., 0:1, :] + x[..., :, 1:2] * y[..., 1:2, :]
            + x[..., :, 2:3] * y[..., 2:3, :])


def mv(x, v):
    """``x @ v``."""
    return x[..., :, 0] * v[..., 0:1] + x[..., :, 1] * v[..., 1:2] + x[..., :, 2] * v[..., 2:3]


def mT(x):
    """Transpose of the trailing 3x3."""
    return jnp.swapaxes(x, -1, -2)


def as_scale(x):
    """Scalar (...,) -> (..., 1, 1) for scaling matrices."""
    return x[..., None, None]


def eye_like(like):
    """The 3x3 identity in the dtype of ``like``."""
    return jnp.eye(3, dtype=like.dtype)


# ---- coefficient functions without sin/cos ----------------------------------------------

# sin(x)/x and (1 - cos x)/x^2 as polynomials in x^2, exact to double precision for
# x^2 <= 2.1 (x = theta / 4 with |theta| <= 1.85 pi); sin/cos are slow on XLA:CPU.
_SINC = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(11))
_COSC = tuple((-1.0) ** k / math.factorial(2 * k + 2) for k in range(11))


def coefficients(s, stage=None):
    """``(a, b, c, d, db, dc)`` of :func:`uavcal_jax.geometry.so3.series_coefficients` at
    ``s = |theta|^2``, computed from quarter-angle polynomials and two angle doublings
    (no sin, cos or sqrt). Accurate to rounding for ``|theta| <= 1.85 pi``. ``stage``
    (the scan's, optional) materialises the two polynomials every coefficient uses."""
    x2 = s * (1.0 / 16.0)
    a4 = so3.horner(_SINC, x2)
    b4 = so3.horner(_COSC, x2)
    if stage is not None:
        ((a4, b4),) = stage((a4, b4))
    a2 = a4 * (1.0 - x2 * b4)  # sin(2x)/(2x) = (sin x / x) cos x
    b2 = 0.5 * a4 * a4  # (1 - cos 2x)/(2x)^2 = (sin x / x)^2 / 2
    a = a2 * (1.0 - 0.25 * s * b2)
    b = 0.5 * a2 * a2
    cos_t = 1.0 - s * b
    small = s < so3.taylor_threshold(s.dtype)
    ss = jnp.where(small, jnp.ones_like(s), s)
    c = jnp.where(small, so3.taylor_series("c", s), (1.0 - a) / ss)
    d = jnp.where(small, so3.taylor_series("d", s), (1.0 - 0.5 * a / b) / ss)
    db = jnp.where(small, so3.taylor_series("db", s), (0.5 * a - b) / ss)
    dc = jnp.where(small, so3.taylor_series("dc", s),
                   (0.5 * (a - cos_t) - c * ss) / (ss * ss))
    return a, b, c, d, db, dc


# ---- component-wise ("batch-last") helpers ---------------------------------------------


def vec_parts(v):
    """(..., 3) -> 3 components."""
    return tuple(v[..., i] for i in range(3))


def mat_parts(m):
    """(..., 3, 3) -> 9 components, row-major."""
    return tuple(m[..., i, j] for i in range(3) for j in range(3))


def vec(parts):
    """3 components -> (..., 3)."""
    return jnp.stack(parts, -1)


def mat(parts):
    """9 row-major components -> (..., 3, 3)."""
    return jnp.stack(parts, -1).reshape(parts[0].shape + (3, 3))


#: (i, j) of the upper triangle of a symmetric 3x3 matrix, row-major
SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def cmm(x, y):
    """``x @ y`` on 9-component matrices."""
    return tuple(x[3 * i] * y[j] + x[3 * i + 1] * y[3 + j] + x[3 * i + 2] * y[6 + j]
                 for i in range(3) for j in range(3))


def cmv(x, v):
    """``x @ v`` on a 9-component matrix and a 3-component vector."""
    return tuple(x[3 * i] * v[0] + x[3 * i + 1] * v[1] + x[3 * i + 2] * v[2] for i in range(3))


def _ccross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _cross_rows(R, a):
    """Rows of ``R`` crossed with ``a`` (``jnp.cross(R, a[None])``)."""
    return sum((_ccross(R[3 * i:3 * i + 3], a) for i in range(3)), ())


def _ci_plus(v, alpha, beta):
    """``I + alpha hat(v) + beta hat(v)^2`` on components."""
    x, y, z = v
    s = x * x + y * y + z * z
    bxy, bxz, byz = beta * x * y, beta * x * z, beta * y * z
    ax, ay, az = alpha * x, alpha * y, alpha * z
    return (1.0 + beta * (x * x - s), bxy - az, bxz + ay,
            bxy + az, 1.0 + beta * (y * y - s), byz - ax,
            bxz - ay, byz + ax, 1.0 + beta * (z * z - s))


def no_stage(*groups):
    """``stage`` for the recursive path: nothing to materialise."""
    return groups


def rotation_step(scheme: str, rot, h, w, a, stage):
    """The rotation part of one sample's step, on components: ``(new_rot, T, V, G, Rn)``
    (see the module docstring); ``rot`` is ``theta`` (3) or ``R`` (9, row-major). ``stage``
    materialises groups of intermediates (:func:`no_stage` for none)."""
    if scheme == "tangent":
        th = rot
        s = th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
        (ca, cb, cc, cd, cdb, cdc), = stage(coefficients(s, stage))
        R, Jr, Ji = stage(_ci_plus(th, ca, cb), _ci_plus(th, -cb, cc),
                          _ci_plus(th, jnp.full_like(cd, 0.5), cd))
        c, = stage(cmv(Ji, w))  # omega in the tangent space at theta
        # D = d(Jr(theta) c)/dtheta at fixed c; d(Jr^-1 omega)/dtheta = -Jr^-1 D
        u = _ccross(th, c)
        q = _ccross(th, u)
        g = tuple(-2.0 * cdb * u[i] + 2.0 * cdc * q[i] - 2.0 * cc * c[i] for i in range(3))
        dot = cc * (th[0] * c[0] + th[1] * c[1] + th[2] * c[2])
        hc = (None, -c[2], c[1], c[2], None, -c[0], -c[1], c[0], None)
        D = []
        for i in range(3):
            for j in range(3):
                d = g[i] * th[j] + cc * th[i] * c[j]
                D.append(d + dot if i == j else d + cb * hc[3 * i + j])
        D, RA = stage(D, _cross_rows(R, a))
        JD, RAJ = stage(cmm(Ji, D), cmm(RA, Jr))
        T = tuple((1.0 if k in (0, 4, 8) else 0.0) - h * JD[k] for k in range(9))
        V = tuple(-h * x for x in RAJ)
        T, V = stage(T, V)
        return tuple(th[i] + h * c[i] for i in range(3)), T, V, Ji, R
    R = rot
    phi = tuple(x * h for x in w)
    s = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    # materialised once: otherwise every entry of dR, G and R dR recomputes them
    (ca, cb, cc), = stage(coefficients(s)[:3])
    dR = _ci_plus(phi, ca, cb)
    G = _ci_plus(phi, -cb, cc)
    V = tuple(-h * x for x in _cross_rows(R, a))
    dRT = tuple(dR[3 * j + i] for i in range(3) for j in range(3))
    return cmm(R, dR), dRT, V, G, R
