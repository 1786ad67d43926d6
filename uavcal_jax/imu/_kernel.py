"""The preintegration kernel: one ``lax.scan`` over the samples, then closed-form sums.

All arrays carry arbitrary leading batch axes ``...`` (so the kernel is natively batched and
also ``vmap``-able); 3x3 matrices are ``(..., 3, 3)``. Products of 3x3 matrices are written as
three broadcast multiply-adds rather than ``dot`` calls: XLA fuses them into element-wise
loops, which is much faster on CPU than many tiny batched matrix multiplications.

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
bias Jacobians equal ``jax.jacfwd`` of the means to rounding.

Covariance, two ways:

``"closed"`` (isotropic noise; the default)
    With ``Q_g = s_g^2 I`` and ``Q_a = s_a^2 I`` the covariance of Forster's on-manifold
    error ``(dphi, dv, dp)`` has a closed form in sums over the samples (the rotations drop
    out because ``R Q R^T = Q``)::

        u_m = dv_N - dv_{m+1},   e_m = dp_N - dp_{m+1} - dv_{m+1} (t_N - t_{m+1})
        phi-phi = s_g^2 t_N I
        phi-v   = s_g^2 R_N^T hat(sum h u),       phi-p = s_g^2 R_N^T hat(sum h e)
        v-v     = s_g^2 sum h (|u|^2 I - u u^T) + s_a^2 t_N I
        v-p     = s_g^2 sum h ((u.e) I - e u^T) + s_a^2 t_N^2/2 I
        p-p     = s_g^2 sum h (|e|^2 I - e e^T) + s_a^2 (t_N^3/3 - sum h^3/12) I

    (``Jr(omega h) Jr(omega h)^T = I`` is taken to hold, a relative error of order
    ``(|omega| h)^2``). For the tangent scheme the rotation rows are then mapped to ``theta``
    with ``Jr(theta_N)^-1``. On EuRoC this agrees with GTSAM's ``preintMeasCov`` to about
    1e-4 relative and costs a few sums instead of a 9x9 congruence per sample. The sums run
    forward inside the scan: with ``y_m = dv_{m+1}`` and ``z_m = dp_{m+1} - t_{m+1} y_m``,
    ``u_m = dv_N - y_m`` and ``e_m = dp_N - t_N y_m - z_m``, so every sum above expands into
    ``t_N``, the end values and the running sums of ``h y``, ``h z``, ``h y y^T``,
    ``h z y^T`` and ``h z z^T`` (no per-sample outputs to store and reduce afterwards).

``"recursive"``
    GTSAM's propagation ``Sigma <- F Sigma F^T + noise`` per sample (9x9, or 15x15 with the
    bias random walks), exact to rounding; used for per-axis noise densities and for
    ``bias_covariance=True``.
"""

from __future__ import annotations

import math
from typing import Any

import jax
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
    return jnp.swapaxes(x, -1, -2)


def hat(v):
    z = jnp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack(
        [jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1), jnp.stack([-y, x, z], -1)], -2
    )


def _s(x):
    """Scalar (...,) -> (..., 1, 1) for scaling matrices."""
    return x[..., None, None]


def _eye(like):
    return jnp.eye(3, dtype=like.dtype)


# ---- coefficient functions without sin/cos ----------------------------------------------

# sin(x)/x and (1 - cos x)/x^2 as polynomials in x^2, exact to double precision for
# x^2 <= 2.1 (x = theta / 4 with |theta| <= 1.85 pi); sin/cos are slow on XLA:CPU.
_SINC = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(11))
_COSC = tuple((-1.0) ** k / math.factorial(2 * k + 2) for k in range(11))


def _horner(coeffs, x):
    out = coeffs[-1]
    for c in coeffs[-2::-1]:
        out = out * x + c
    return out


def coefficients(s, stage=None):
    """``(a, b, c, d, db, dc)`` of :func:`uavcal_jax.geometry.so3.series_coefficients` at
    ``s = |theta|^2``, computed from quarter-angle polynomials and two angle doublings
    (no sin, cos or sqrt). Accurate to rounding for ``|theta| <= 1.85 pi``. ``stage``
    (the scan's, optional) materialises the two polynomials every coefficient uses."""
    x2 = s * (1.0 / 16.0)
    a4 = _horner(_SINC, x2)
    b4 = _horner(_COSC, x2)
    if stage is not None:
        ((a4, b4),) = stage((a4, b4))
    a2 = a4 * (1.0 - x2 * b4)  # sin(2x)/(2x) = (sin x / x) cos x
    b2 = 0.5 * a4 * a4  # (1 - cos 2x)/(2x)^2 = (sin x / x)^2 / 2
    a = a2 * (1.0 - 0.25 * s * b2)
    b = 0.5 * a2 * a2
    cos_t = 1.0 - s * b
    small = s < so3._switch(s.dtype)
    ss = jnp.where(small, jnp.ones_like(s), s)
    tay = so3._TAYLOR
    c = jnp.where(small, so3._poly(tay["c"], s), (1.0 - a) / ss)
    d = jnp.where(small, so3._poly(tay["d"], s), (1.0 - 0.5 * a / b) / ss)
    db = jnp.where(small, so3._poly(tay["db"], s), (0.5 * a - b) / ss)
    dc = jnp.where(small, so3._poly(tay["dc"], s), (0.5 * (a - cos_t) - c * ss) / (ss * ss))
    return a, b, c, d, db, dc


def _recursive_noise(n: int, h, G, Rn, var):
    """Discrete noise covariance added per step, internal order (rot, p, v[, bg, ba])."""
    qg = jnp.stack(var["gyro"], -1)
    qa = jnp.stack(var["accel"], -1)
    qi = jnp.stack(var["integration"], -1)
    hs = _s(h)
    GQG = mm(G * qg[..., None, :], mT(G)) * hs
    M = mm(Rn * qa[..., None, :], mT(Rn))
    Z = jnp.zeros_like(M)
    blocks = [
        [GQG, Z, Z],
        [Z, M * hs * hs * hs * 0.25 + hs * qi[..., None, :] * _eye(M), M * hs * hs * 0.5],
        [Z, M * hs * hs * 0.5, M * hs],
    ]
    if n == 15:
        qbg = jnp.stack(var["gyro_rw"], -1)
        qba = jnp.stack(var["accel_rw"], -1)
        for row in blocks:
            row.extend([Z, Z])
        blocks.append([Z, Z, Z, hs * qbg[..., None, :] * _eye(M), Z])
        blocks.append([Z, Z, Z, Z, hs * qba[..., None, :] * _eye(M)])
    return jnp.concatenate([jnp.concatenate(r, -1) for r in blocks], -2)


def _transition(n: int, h, T, V, G, Rn):
    """The dense transition F of the (rot, p, v[, bg, ba]) error for one step."""
    hs = _s(h)
    I = jnp.broadcast_to(_eye(T), T.shape)
    Z = jnp.zeros_like(T)
    rows = [[T, Z, Z], [V * hs * 0.5, I, I * hs], [V, Z, I]]
    if n == 15:
        # bias drift acts like a measurement perturbation: +C (gyro), +B (accel)
        rows[0].extend([G * hs, Z])
        rows[1].extend([Z, Rn * hs * hs * 0.5])
        rows[2].extend([Z, Rn * hs])
        rows.append([Z, Z, Z, I, Z])
        rows.append([Z, Z, Z, Z, I])
    return jnp.concatenate([jnp.concatenate(r, -1) for r in rows], -2)


# ---- component-wise ("batch-last") form of the scan -----------------------------------
#
# The rotation step is written on *components* (both paths use it; the recursive one then
# stacks T, V, G, Rn into matrices for its 9x9 / 15x15 propagation), and for the closed-form
# covariance so is the whole scan: a vector is a tuple of
# 3 arrays and a 3x3 matrix a row-major tuple of 9 arrays, each of the batch shape ``...``.
# Every operation in the loop body is then element-wise over the whole batch (contiguous,
# SIMD-vectorised loops over the windows) instead of loops over tiny trailing 3 / 3x3 axes,
# and this holds natively batched and under ``jax.vmap`` alike. The mean and Jacobian
# updates are those of the recursive ``step`` in :func:`run` (a few regrouped, see below:
# equal to rounding).
#
# On XLA:CPU a step costs about a microsecond per kernel launched, so the structure is
# tuned by measurement (``experiments/bench_preintegration.py``): per-component carries with
# ``stage`` barriers beat stacked (9, B) groups and a blocked or parallel-in-time split of
# the step (heavier kernels get split across threads, whose hand-off costs more than they
# save at these sizes). A carry packed into a few stacked arrays, each written by one kernel
# (XLA:CPU fuses a concatenation of at most 8 operands, so nested stacks of 8), cuts the
# kernels per step from ~180 to ~20 but measured 1.5x slower: under ``vmap`` a scan carries
# non-scalar leaves batch-major, and the fused concatenations do not vectorise.


def _vec_parts(v):
    """(..., 3) -> 3 components."""
    return tuple(v[..., i] for i in range(3))


def _mat_parts(m):
    """(..., 3, 3) -> 9 components, row-major."""
    return tuple(m[..., i, j] for i in range(3) for j in range(3))


def _vec(parts):
    """3 components -> (..., 3)."""
    return jnp.stack(parts, -1)


def _mat(parts):
    """9 row-major components -> (..., 3, 3)."""
    return jnp.stack(parts, -1).reshape(parts[0].shape + (3, 3))


#: (i, j) of the upper triangle of a symmetric 3x3 matrix, row-major
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _cmm(x, y):
    return tuple(x[3 * i] * y[j] + x[3 * i + 1] * y[3 + j] + x[3 * i + 2] * y[6 + j]
                 for i in range(3) for j in range(3))


def _cmv(x, v):
    return tuple(x[3 * i] * v[0] + x[3 * i + 1] * v[1] + x[3 * i + 2] * v[2] for i in range(3))


def _ccross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _cross_rows(R, a):
    """Rows of ``R`` crossed with ``a`` (``jnp.cross(R, a[None])``)."""
    return sum((_ccross(R[3 * i:3 * i + 3], a) for i in range(3)), ())


def _ci_plus(v, alpha, beta):
    x, y, z = v
    s = x * x + y * y + z * z
    bxy, bxz, byz = beta * x * y, beta * x * z, beta * y * z
    ax, ay, az = alpha * x, alpha * y, alpha * z
    return (1.0 + beta * (x * x - s), bxy - az, bxz + ay,
            bxy + az, 1.0 + beta * (y * y - s), byz - ax,
            bxz - ay, byz + ax, 1.0 + beta * (z * z - s))


def _no_stage(*groups):
    """``stage`` for the recursive path: nothing to materialise."""
    return groups


def _crot_step(scheme: str, rot, h, w, a, stage):
    """The rotation part of one sample's step, on components: ``(new_rot, T, V, G, Rn)``
    (see the module docstring); ``rot`` is ``theta`` (3) or ``R`` (9, row-major)."""
    if scheme == "tangent":
        th = rot
        s = th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
        (ca, cb, cc, cd, cdb, cdc), = stage(coefficients(s, stage))
        R, Jr, Ji = stage(_ci_plus(th, ca, cb), _ci_plus(th, -cb, cc),
                          _ci_plus(th, jnp.full_like(cd, 0.5), cd))
        c, = stage(_cmv(Ji, w))  # omega in the tangent space at theta
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
        JD, RAJ = stage(_cmm(Ji, D), _cmm(RA, Jr))
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
    return _cmm(R, dR), dRT, V, G, R


def _run_components(comps, var: dict, scheme: str, unroll: int) -> dict[str, Any]:
    """:func:`run` for ``covariance="closed"`` with the scan on components (see above)."""
    # time-major components (N, ...): the scan reads one contiguous slice of each per
    # sample, natively batched and under vmap alike
    xs = tuple(jnp.moveaxis(c, -1, 0) for c in comps)
    z = jnp.zeros_like(xs[0][0])  # inherits sharding / varying axes (shard_map)
    one = jnp.ones_like(z)
    z3, z6, z9 = (z,) * 3, (z,) * 6, (z,) * 9
    eye9 = (one, z, z, z, one, z, z, z, one)
    carry = {"rot": z3 if scheme == "tangent" else eye9, "p": z3, "v": z3, "Hr": z9, "Hv": z9,
             "Hp": z9, "Hva": z9, "Hpa": z9, "t": z,
             "Y": z3, "Z": z3, "Syy": z6, "Szy": z9, "Szz": z6}
    # H_rot_bg is carried as one stacked (9, ...) array: each new entry reads three old ones,
    # so as separate arrays XLA would copy the old ones before overwriting them (9 copies per
    # sample); stacking other groups measured slower
    carry["Hr"] = jnp.stack(carry["Hr"])

    def add(x, y):
        return tuple(xi + yi for xi, yi in zip(x, y, strict=True))

    def scale(k, x):
        return tuple(k * xi for xi in x)

    def stage(*groups):
        # materialise intermediates shared by many outputs: without the barrier XLA fuses
        # them into every consumer and recomputes them (e.g. the coefficients per entry)
        flat = [x for g in groups for x in g]
        st = jax.lax.optimization_barrier(jnp.stack(flat, 0))
        out, i = [], 0
        for g in groups:
            out.append(tuple(st[i + j] for j in range(len(g))))
            i += len(g)
        return tuple(out)

    def step(c, x):
        c = dict(c, Hr=tuple(c["Hr"]))
        h_k, w_k, a_k = x[0], x[1:4], x[4:7]
        new_rot, T, V, G, Rn = _crot_step(scheme, c["rot"], h_k, w_k, a_k, stage)
        an, VH = stage(_cmv(Rn, a_k), _cmm(V, c["Hr"]))
        # position-like updates read the *new* velocity-like values (x + h y_old + h^2/2 q
        # == x + h y_new - h^2/2 q when y_new = y_old + h q), so every carry is dead once
        # its successor is written and XLA updates it in place instead of copying it
        v = add(c["v"], scale(h_k, an))
        p = tuple(c["p"][i] + h_k * v[i] - 0.5 * h_k * h_k * an[i] for i in range(3))
        t = c["t"] + h_k
        zq = tuple(p[i] - t * v[i] for i in range(3))
        hv, hz = scale(h_k, v), scale(h_k, zq)
        Hv = add(c["Hv"], VH)
        Hva = tuple(x - h_k * r for x, r in zip(c["Hva"], Rn, strict=True))
        new = {
            "rot": new_rot, "p": p, "v": v,
            "Hr": tuple(x - h_k * g for x, g in zip(_cmm(T, c["Hr"]), G, strict=True)),
            "Hv": Hv,
            "Hp": tuple(hp + h_k * hv - 0.5 * h_k * vh
                        for hp, hv, vh in zip(c["Hp"], Hv, VH, strict=True)),
            "Hva": Hva,
            "Hpa": tuple(x + h_k * y + 0.5 * h_k * h_k * r
                         for x, y, r in zip(c["Hpa"], Hva, Rn, strict=True)),
            "t": t,
            "Y": add(c["Y"], hv), "Z": add(c["Z"], hz),
            "Syy": add(c["Syy"], tuple(hv[i] * v[j] for i, j in _SYM)),
            "Szy": add(c["Szy"], tuple(hz[i] * v[j] for i in range(3) for j in range(3))),
            "Szz": add(c["Szz"], tuple(hz[i] * zq[j] for i, j in _SYM)),
        }  # fmt: skip
        new["Hr"] = jnp.stack(new["Hr"])
        return new, None

    out, _ = jax.lax.scan(step, carry, xs, unroll=unroll)
    out["Hr"] = tuple(out["Hr"])

    def sym(parts):  # upper triangle of a symmetric matrix -> (..., 3, 3)
        return _mat([parts[_SYM.index((min(i, j), max(i, j)))] for i in range(3)
                     for j in range(3)])

    res: dict[str, Any] = {k: _vec(out[k]) if len(out[k]) == 3 else _mat(out[k])
                           for k in ("rot", "p", "v", "Hr", "Hv", "Hp", "Hva", "Hpa")}
    res["t"] = out["t"]
    t_n, v, p, Y, Z = _s(out["t"]), res["v"], res["p"], _vec(out["Y"]), _vec(out["Z"])
    Syy, Szy, Szz = sym(out["Syy"]), _mat(out["Szy"]), sym(out["Szz"])

    def o(x, y):
        return x[..., :, None] * y[..., None, :]

    sums = {
        "su": t_n[..., 0] * v - Y,
        "se": t_n[..., 0] * (p - Y) - Z,
        "Suu": t_n * o(v, v) - o(v, Y) - o(Y, v) + Syy,
        "Sue": t_n * (o(p, v) - o(Y, v) + Syy) - o(p, Y) - o(Z, v) + Szy,
        "See": (t_n * (o(p, p) - o(p, Y) - o(Y, p) + Szy + mT(Szy)) - o(p, Z) - o(Z, p)
                + t_n * t_n * Syy + Szz),
        "s3": jnp.sum(xs[0] * xs[0] * xs[0], 0),
    }
    res["cov"] = _closed_assemble(res, sums, var, scheme)
    return res


def run(comps, var: dict, scheme: str, covariance: str, n_cov: int, unroll: int
        ) -> dict[str, Any]:
    """Scan over the samples. ``comps``: seven (..., N) arrays, the hold time and the gyro and
    accel axes per sample (bias-corrected, masked samples zeroed with hold time 0). Returns a
    dict of arrays (see ``preintegrate``)."""
    if covariance == "closed":
        return _run_components(comps, var, scheme, unroll)
    h = comps[0]
    z = jnp.zeros_like(h[..., 0])  # inherits sharding / varying axes (shard_map)
    z3 = jnp.stack([z] * 3, -1)
    z33 = jnp.stack([z3] * 3, -1)
    eye = z33 + jnp.eye(3, dtype=h.dtype)
    carry: dict[str, Any] = {
        "rot": z3 if scheme == "tangent" else eye,
        "p": z3, "v": z3,
        "Hr": z33, "Hv": z33, "Hp": z33, "Hva": z33, "Hpa": z33,
    }  # fmt: skip
    carry["cov"] = jnp.zeros_like(z[..., None, None]) + jnp.zeros((n_cov, n_cov), h.dtype)

    def step(c, x):
        h_k, w_k, a_k = x[0], x[1:4], x[4:7]
        hs = _s(h_k)
        rot = _vec_parts(c["rot"]) if scheme == "tangent" else _mat_parts(c["rot"])
        new_rot, T, V, G, Rn = _crot_step(scheme, rot, h_k, w_k, a_k, _no_stage)
        new_rot = _vec(new_rot) if scheme == "tangent" else _mat(new_rot)
        T, V, G, Rn = (_mat(m) for m in (T, V, G, Rn))
        an = mv(Rn, _vec(a_k))
        hv = h_k[..., None]
        VH = mm(V, c["Hr"])
        new = {
            "rot": new_rot,
            "p": c["p"] + hv * c["v"] + 0.5 * hv * hv * an,
            "v": c["v"] + hv * an,
            "Hr": mm(T, c["Hr"]) - hs * G,
            "Hv": c["Hv"] + VH,
            "Hp": c["Hp"] + hs * c["Hv"] + 0.5 * hs * VH,
            "Hva": c["Hva"] - hs * Rn,
            "Hpa": c["Hpa"] + hs * c["Hva"] - 0.5 * hs * hs * Rn,
        }
        F = _transition(n_cov, h_k, T, V, G, Rn)
        new["cov"] = F @ c["cov"] @ mT(F) + _recursive_noise(n_cov, h_k, G, Rn, var)
        return new, None

    xs = tuple(jnp.moveaxis(c, -1, 0) for c in comps)  # time-major (N, ...) each
    out, _ = jax.lax.scan(step, carry, xs, unroll=unroll)
    out["t"] = jnp.sum(h, -1)
    return out


def _closed_assemble(out, sums, var, scheme: str):
    """Isotropic closed form (see the module docstring), order (rot, p, v), from the sums
    ``su = sum h u``, ``se = sum h e``, ``Suu = sum h u u^T``, ``Sue = sum h e u^T``,
    ``See = sum h e e^T`` and ``s3 = sum h^3``."""
    qg = var["gyro"][0]
    qa = var["accel"][0]
    qi = jnp.stack(var["integration"], -1)
    t_n = out["t"]
    su, se, Suu, Sue, See, s3 = (sums[k] for k in ("su", "se", "Suu", "Sue", "See", "s3"))
    eye = _eye(t_n)

    def tr(m):
        return m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]

    R_n = so3.exp(out["rot"]) if scheme == "tangent" else out["rot"]
    qg_, qa_ = _s(jnp.asarray(qg)), _s(jnp.asarray(qa))
    rr = qg_ * _s(t_n) * eye
    rv = qg_ * mm(mT(R_n), hat(su))
    rp = qg_ * mm(mT(R_n), hat(se))
    vv = qg_ * (_s(tr(Suu)) * eye - Suu) + qa_ * _s(t_n) * eye
    vp = qg_ * (_s(tr(Sue)) * eye - Sue) + qa_ * _s(0.5 * t_n * t_n) * eye
    pp = (qg_ * (_s(tr(See)) * eye - See) + qa_ * _s(t_n * t_n * t_n / 3.0 - s3 / 12.0) * eye
          + _s(t_n) * qi[..., None, :] * eye)
    if scheme == "tangent":
        Ji = so3.right_jacobian_inv(out["rot"])
        rr = qg_ * _s(t_n) * mm(Ji, mT(Ji))
        rv = mm(Ji, rv)
        rp = mm(Ji, rp)
    return jnp.concatenate(
        [
            jnp.concatenate([rr, rp, rv], -1),
            jnp.concatenate([mT(rp), pp, mT(vp)], -1),
            jnp.concatenate([mT(rv), vp, vv], -1),
        ],
        -2,
    )
