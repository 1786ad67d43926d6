"""The preintegration scan with GTSAM's recursive covariance propagation.

Per sample, ``Sigma <- F Sigma F^T + noise`` on the error ``(rot, p, v)`` (9x9), or
``(rot, p, v, bg, ba)`` (15x15) with the bias random walks (GTSAM's
``PreintegratedCombinedMeasurements``): exact to rounding, and what per-axis noise densities
and ``bias_covariance=True`` need. The mean and bias-Jacobian updates are those of
:mod:`uavcal_jax.imu._ops`, here on ``(..., 3)`` / ``(..., 3, 3)`` arrays.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from uavcal_jax.imu._ops import (
    as_scale,
    eye_like,
    mat,
    mat_parts,
    mm,
    mT,
    mv,
    no_stage,
    rotation_step,
    vec,
    vec_parts,
)


def _noise(n: int, h, G, Rn, var):
    """Discrete noise covariance added per step, internal order (rot, p, v[, bg, ba])."""
    qg = jnp.stack(var["gyro"], -1)
    qa = jnp.stack(var["accel"], -1)
    qi = jnp.stack(var["integration"], -1)
    hs = as_scale(h)
    GQG = mm(G * qg[..., None, :], mT(G)) * hs
    M = mm(Rn * qa[..., None, :], mT(Rn))
    Z = jnp.zeros_like(M)
    blocks = [
        [GQG, Z, Z],
        [Z, M * hs * hs * hs * 0.25 + hs * qi[..., None, :] * eye_like(M), M * hs * hs * 0.5],
        [Z, M * hs * hs * 0.5, M * hs],
    ]
    if n == 15:
        qbg = jnp.stack(var["gyro_rw"], -1)
        qba = jnp.stack(var["accel_rw"], -1)
        for row in blocks:
            row.extend([Z, Z])
        blocks.append([Z, Z, Z, hs * qbg[..., None, :] * eye_like(M), Z])
        blocks.append([Z, Z, Z, Z, hs * qba[..., None, :] * eye_like(M)])
    return jnp.concatenate([jnp.concatenate(r, -1) for r in blocks], -2)


def _transition(n: int, h, T, V, G, Rn):
    """The dense transition F of the (rot, p, v[, bg, ba]) error for one step."""
    hs = as_scale(h)
    I = jnp.broadcast_to(eye_like(T), T.shape)
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


def run(comps, var: dict, scheme: str, n_cov: int, unroll: int) -> dict[str, Any]:
    """Scan over the samples. ``comps``: seven (..., N) arrays, the hold time and the gyro and
    accel axes per sample (bias-corrected, masked samples zeroed with hold time 0); ``var``:
    ``ImuNoise.variances``; ``n_cov``: 9 or 15. Returns ``rot`` (``theta`` (..., 3) or ``R``
    (..., 3, 3)), ``p``, ``v``, the bias Jacobians ``Hr``, ``Hv``, ``Hp``, ``Hva``, ``Hpa``
    (..., 3, 3), ``t`` (...) and ``cov`` (..., n_cov, n_cov) in the order (rot, p, v[, bg,
    ba])."""
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
        hs = as_scale(h_k)
        rot = vec_parts(c["rot"]) if scheme == "tangent" else mat_parts(c["rot"])
        new_rot, T, V, G, Rn = rotation_step(scheme, rot, h_k, w_k, a_k, no_stage)
        new_rot = vec(new_rot) if scheme == "tangent" else mat(new_rot)
        T, V, G, Rn = (mat(m) for m in (T, V, G, Rn))
        an = mv(Rn, vec(a_k))
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
        new["cov"] = F @ c["cov"] @ mT(F) + _noise(n_cov, h_k, G, Rn, var)
        return new, None

    xs = tuple(jnp.moveaxis(c, -1, 0) for c in comps)  # time-major (N, ...) each
    out, _ = jax.lax.scan(step, carry, xs, unroll=unroll)
    out["t"] = jnp.sum(h, -1)
    return out
