"""The preintegration scan with the closed-form (isotropic-noise) covariance.

With ``Q_g = s_g^2 I`` and ``Q_a = s_a^2 I`` the covariance of Forster's on-manifold error
``(dphi, dv, dp)`` has a closed form in sums over the samples (the rotations drop out because
``R Q R^T = Q``)::

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

The whole scan runs on components (see :mod:`uavcal_jax.imu._ops`); its mean and Jacobian
updates are those of :mod:`uavcal_jax.imu._recursive` (a few regrouped, see below: equal to
rounding).

On XLA:CPU a step costs about a microsecond per kernel launched, so the structure is
tuned by measurement (``experiments/bench_preintegration.py``): per-component carries with
``stage`` barriers beat stacked (9, B) groups and a blocked or parallel-in-time split of
the step (heavier kernels get split across threads, whose hand-off costs more than they
save at these sizes). A carry packed into a few stacked arrays, each written by one kernel
(XLA:CPU fuses a concatenation of at most 8 operands, so nested stacks of 8), cuts the
kernels per step from ~180 to ~20 but measured 1.5x slower: under ``vmap`` a scan carries
non-scalar leaves batch-major, and the fused concatenations do not vectorise.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from uavcal_jax.geometry import so3
from uavcal_jax.imu._ops import (
    SYM,
    as_scale,
    cmm,
    cmv,
    eye_like,
    mat,
    mm,
    mT,
    rotation_step,
    vec,
)


def run(comps, var: dict, scheme: str, unroll: int) -> dict[str, Any]:
    """Scan over the samples with the closed-form covariance. ``comps``: seven (..., N)
    arrays, the hold time and the gyro and accel axes per sample (bias-corrected, masked
    samples zeroed with hold time 0); ``var``: ``ImuNoise.variances``. Returns the dict of
    :func:`uavcal_jax.imu._recursive.run` (``cov`` 9x9, order (rot, p, v))."""
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
        new_rot, T, V, G, Rn = rotation_step(scheme, c["rot"], h_k, w_k, a_k, stage)
        an, VH = stage(cmv(Rn, a_k), cmm(V, c["Hr"]))
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
            "Hr": tuple(x - h_k * g for x, g in zip(cmm(T, c["Hr"]), G, strict=True)),
            "Hv": Hv,
            "Hp": tuple(hp + h_k * hv - 0.5 * h_k * vh
                        for hp, hv, vh in zip(c["Hp"], Hv, VH, strict=True)),
            "Hva": Hva,
            "Hpa": tuple(x + h_k * y + 0.5 * h_k * h_k * r
                         for x, y, r in zip(c["Hpa"], Hva, Rn, strict=True)),
            "t": t,
            "Y": add(c["Y"], hv), "Z": add(c["Z"], hz),
            "Syy": add(c["Syy"], tuple(hv[i] * v[j] for i, j in SYM)),
            "Szy": add(c["Szy"], tuple(hz[i] * v[j] for i in range(3) for j in range(3))),
            "Szz": add(c["Szz"], tuple(hz[i] * zq[j] for i, j in SYM)),
        }  # fmt: skip
        new["Hr"] = jnp.stack(new["Hr"])
        return new, None

    out, _ = jax.lax.scan(step, carry, xs, unroll=unroll)
    out["Hr"] = tuple(out["Hr"])

    def sym(parts):  # upper triangle of a symmetric matrix -> (..., 3, 3)
        return mat([parts[SYM.index((min(i, j), max(i, j)))] for i in range(3)
                    for j in range(3)])

    res: dict[str, Any] = {k: vec(out[k]) if len(out[k]) == 3 else mat(out[k])
                           for k in ("rot", "p", "v", "Hr", "Hv", "Hp", "Hva", "Hpa")}
    res["t"] = out["t"]
    t_n, v, p, Y, Z = as_scale(out["t"]), res["v"], res["p"], vec(out["Y"]), vec(out["Z"])
    Syy, Szy, Szz = sym(out["Syy"]), mat(out["Szy"]), sym(out["Szz"])

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
    res["cov"] = _assemble(res, sums, var, scheme)
    return res


def _assemble(out, sums, var, scheme: str):
    """Isotropic closed form (see the module docstring), order (rot, p, v), from the sums
    ``su = sum h u``, ``se = sum h e``, ``Suu = sum h u u^T``, ``Sue = sum h e u^T``,
    ``See = sum h e e^T`` and ``s3 = sum h^3``."""
    qg = var["gyro"][0]
    qa = var["accel"][0]
    qi = jnp.stack(var["integration"], -1)
    t_n = out["t"]
    su, se, Suu, Sue, See, s3 = (sums[k] for k in ("su", "se", "Suu", "Sue", "See", "s3"))
    eye = eye_like(t_n)

    def tr(m):
        return m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]

    S = as_scale
    R_n = so3.exp(out["rot"]) if scheme == "tangent" else out["rot"]
    qg_, qa_ = S(jnp.asarray(qg)), S(jnp.asarray(qa))
    rr = qg_ * S(t_n) * eye
    rv = qg_ * mm(mT(R_n), so3.hat(su))
    rp = qg_ * mm(mT(R_n), so3.hat(se))
    vv = qg_ * (S(tr(Suu)) * eye - Suu) + qa_ * S(t_n) * eye
    vp = qg_ * (S(tr(Sue)) * eye - Sue) + qa_ * S(0.5 * t_n * t_n) * eye
    pp = (qg_ * (S(tr(See)) * eye - See) + qa_ * S(t_n * t_n * t_n / 3.0 - s3 / 12.0) * eye
          + S(t_n) * qi[..., None, :] * eye)
    if scheme == "tangent":
        Ji = so3.right_jacobian_inv(out["rot"])
        rr = qg_ * S(t_n) * mm(Ji, mT(Ji))
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
