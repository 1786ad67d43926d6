"""On-manifold IMU preintegration (Forster et al.; GTSAM; RPEOD sec. 3.2) as a ``lax.scan``.

:func:`preintegrate` integrates the IMU samples of one interval (or of many intervals at once)
into the relative motion ``(delta_R, delta_v, delta_p)`` over ``delta_t``, the Jacobians of
those deltas with respect to the gyro and accelerometer biases, and the covariance of the
preintegration error propagated from the noise densities. Sample ``k`` is held constant for
``dt[k]`` seconds, exactly as GTSAM's ``integrateMeasurement(acc, gyro, dt)`` takes it;
:mod:`uavcal_jax.imu.interval` cuts ``[t_i, t_j]`` out of a timestamped stream, interpolating
at the interval ends.

Two integration schemes (``scheme=``):

``"tangent"`` (default)
    GTSAM 4.3's default (``TangentPreintegration``, the scheme of the ``gtsam`` pip wheel):
    the rotation is integrated as a rotation vector ``theta`` in the tangent space at the
    start of the interval, ``theta += Jr(theta)^-1 omega dt``, ``delta_R = exp(theta)``;
    position and velocity with the rotation at the start of each step. Means and bias
    Jacobians reproduce GTSAM's to rounding error (1e-15 on the EuRoC checks); the bias
    Jacobians are the exact derivatives of the means (``jax.jacfwd`` agrees to rounding).
    The covariance is that of ``(theta, delta_v, delta_p)``. Rotation vectors must stay
    below ``2 pi`` in length over one interval (``Jr^-1`` is singular there): a result whose
    ``|theta|`` exceeds :data:`THETA_LIMIT` is flagged invalid -- use ``"manifold"`` or
    shorter intervals for such rates.

``"manifold"``
    The plain Euler on-manifold scheme of Forster et al. (RPEOD eqs. 3-5; VINS-Mono without
    the mid-point rule): ``delta_R <- delta_R exp(omega dt)``,
    ``delta_v <- delta_v + delta_R a dt``, ``delta_p <- delta_p + delta_v dt + delta_R a dt^2/2``;
    bias Jacobians and covariance of the right-perturbation error ``(dphi, dv, dp)`` as in
    Forster's appendix. It agrees with GTSAM's tangent update to about 3e-5 (rad, m/s, m)
    over 1 s of EuRoC V1_01, and its covariance diagonal to about 4 % (the rotation block is
    in different coordinates).

Covariance (``covariance=``): ``"closed"`` (default for scalar noise densities) evaluates
the isotropic-noise closed form of the on-manifold covariance from sums over the samples
(and maps its rotation rows to ``theta`` for the tangent scheme); it matches GTSAM's
``preintMeasCov()`` to about 1e-4 relative on EuRoC. ``"recursive"`` (used for per-axis
densities and ``bias_covariance=True``) propagates ``Sigma <- F Sigma F^T + noise`` per
sample exactly as GTSAM does (to rounding). With ``bias_covariance=True`` the state is
extended by the two biases, which random-walk with the given densities (GTSAM's
``PreintegratedCombinedMeasurements``), and ``cov`` is 15x15. See
:mod:`uavcal_jax.imu._ops` for the step's recursions, :mod:`uavcal_jax.imu._closed` for the
closed form and :mod:`uavcal_jax.imu._recursive` for GTSAM's propagation.

Orders: every output follows the **rotation, velocity, position** order (then gyro bias,
accel bias). GTSAM's ``preintMeasCov()`` is in rotation, position, velocity order (and
accel bias before gyro bias for the combined factor).

Bad input: NaN or infinite samples, non-positive time steps, biases or offsets that are not
finite, and intervals without any sample raise :class:`~uavcal_jax.errors.DataError` when
called eagerly with concrete arrays. Under ``jit``/``vmap``/``grad`` (traced arrays) nothing can
be raised: the offending samples are skipped (treated as masked), every output stays finite,
and the result's ``valid`` flag is ``False``. Always check ``valid`` on traced results.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.errors import DataError
from uavcal_jax.geometry import so3
from uavcal_jax.imu import _closed, _recursive
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise

__all__ = [
    "Preintegrated",
    "preintegrate",
    "bias_correct",
    "SCHEMES",
    "THETA_LIMIT",
]

#: Integration schemes accepted by :func:`preintegrate`.
SCHEMES = ("tangent", "manifold")

#: Largest ``|theta|`` (rad) accepted by the tangent scheme before the result is flagged
#: invalid (``Jr(theta)^-1`` is singular at ``2 pi``).
THETA_LIMIT = 1.8 * np.pi


@dataclasses.dataclass(frozen=True)
class Preintegrated:
    """Result of :func:`preintegrate` (a pytree; leading batch axes ``...`` on every field).

    Attributes:
        delta_R: (..., 3, 3) rotation from the body frame at ``t_j`` to the body frame at ``t_i``.
        delta_v: (..., 3) velocity increment in the frame at ``t_i`` (gravity excluded), m/s.
        delta_p: (..., 3) position increment in the frame at ``t_i`` (gravity excluded), m.
        delta_t: (...) integrated time, s.
        theta: (..., 3) rotation vector of ``delta_R`` (tangent scheme: GTSAM's
            ``preintegrated()[:3]``, not wrapped to ``[0, pi]``).
        d_R_d_bg: (..., 3, 3) right-perturbation Jacobian of ``delta_R`` w.r.t. the gyro bias:
            ``delta_R(bg + d) ~= delta_R exp(d_R_d_bg @ d)``.
        d_theta_d_bg: (..., 3, 3) Jacobian of ``theta`` w.r.t. the gyro bias (GTSAM's
            ``preintegrated_H_biasOmega`` rows 0-2).
        d_v_d_bg, d_v_d_ba, d_p_d_bg, d_p_d_ba: (..., 3, 3) Jacobians of ``delta_v``,
            ``delta_p`` w.r.t. the gyro / accel bias.
        cov: (..., 9, 9) covariance of the preintegration error, order (rotation, velocity,
            position); rotation as ``theta`` for the tangent scheme, as the right perturbation of
            ``delta_R`` for the manifold scheme. (..., 15, 15) with ``bias_covariance=True``:
            (rotation, velocity, position, gyro bias, accel bias), the bias blocks being the
            random walk over ``delta_t`` and its correlation with the deltas.
        cov_bias: (..., 6, 6) random-walk covariance of the bias change over the interval
            (gyro, accel), ``density^2 * delta_t``.
        bias_gyro, bias_accel: (..., 3) the biases the samples were integrated with.
        valid: (...) bool; ``False`` when samples were bad, the interval empty, or the result
            is not finite / out of the scheme's range (see the module docstring).
        n_samples: (...) int32, samples integrated (masked and bad ones excluded).
        scheme: ``"tangent"`` or ``"manifold"`` (static).
    """

    delta_R: jax.Array
    delta_v: jax.Array
    delta_p: jax.Array
    delta_t: jax.Array
    theta: jax.Array
    d_R_d_bg: jax.Array
    d_theta_d_bg: jax.Array
    d_v_d_bg: jax.Array
    d_v_d_ba: jax.Array
    d_p_d_bg: jax.Array
    d_p_d_ba: jax.Array
    cov: jax.Array
    cov_bias: jax.Array
    bias_gyro: jax.Array
    bias_accel: jax.Array
    valid: jax.Array
    n_samples: jax.Array
    scheme: str = "tangent"

    @property
    def bias_jacobian(self) -> jax.Array:
        """(..., 9, 6): rows (rotation, velocity, position), columns (gyro bias, accel bias);
        the rotation rows are ``d_R_d_bg`` (right perturbation) and zeros."""
        zero = jnp.zeros_like(self.d_R_d_bg)
        top = jnp.concatenate([self.d_R_d_bg, zero], axis=-1)
        mid = jnp.concatenate([self.d_v_d_bg, self.d_v_d_ba], axis=-1)
        bot = jnp.concatenate([self.d_p_d_bg, self.d_p_d_ba], axis=-1)
        return jnp.concatenate([top, mid, bot], axis=-2)

    @property
    def gtsam_cov(self) -> jax.Array:
        """``cov`` permuted to GTSAM's ``preintMeasCov()`` order: (rotation, position,
        velocity) and, for the 15x15 form, (accel bias, gyro bias) after them."""
        n = self.cov.shape[-1]
        perm = [0, 1, 2, 6, 7, 8, 3, 4, 5]
        if n == 15:
            perm += [12, 13, 14, 9, 10, 11]
        perm = np.asarray(perm)
        return self.cov[..., perm[:, None], perm[None, :]]


jax.tree_util.register_dataclass(
    Preintegrated,
    data_fields=[f.name for f in dataclasses.fields(Preintegrated) if f.name != "scheme"],
    meta_fields=["scheme"],
)


# --------------------------------------------------------------------------------------
# Input handling
# --------------------------------------------------------------------------------------


def _is_traced(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def _float_dtype(*xs):
    dtype = jnp.result_type(*[x.dtype for x in xs])
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _check_shapes(dt, gyro, accel, mask) -> None:
    if gyro.ndim < 2 or gyro.shape[-1] != 3:
        raise DataError(f"gyro must be (..., N, 3), got shape {gyro.shape}")
    if accel.shape != gyro.shape:
        raise DataError(f"accel shape {accel.shape} differs from gyro shape {gyro.shape}")
    if dt.shape != gyro.shape[:-1]:
        raise DataError(f"dt must be (..., N) = {gyro.shape[:-1]}, got shape {dt.shape}")
    if mask is not None and mask.shape != dt.shape:
        raise DataError(f"mask shape {mask.shape} differs from dt shape {dt.shape}")


_BAD_KIND = {1: "non-finite dt", 2: "dt <= 0", 3: "non-finite gyro/accel"}


def _sample_ok(dt, gyro, accel):
    return (jnp.isfinite(dt) & (dt > 0) & jnp.all(jnp.isfinite(gyro), -1)
            & jnp.all(jnp.isfinite(accel), -1))


def _eager_check(dt, gyro, accel, mask, bg, ba, off) -> None:
    """Raise a DataError describing the first problems (concrete arrays only)."""
    dt, gyro, accel, mask = (np.asarray(x) for x in (dt, gyro, accel, mask))
    if not (np.all(np.isfinite(np.asarray(bg))) and np.all(np.isfinite(np.asarray(ba)))
            and np.all(np.isfinite(np.asarray(off)))):
        raise DataError("preintegrate: bias_gyro / bias_accel / offset contain NaN or inf")
    with np.errstate(invalid="ignore"):
        kind = np.where(~np.isfinite(dt), 1, np.where(~(dt > 0), 2, 0))
    kind = np.where((kind == 0) & ~(np.all(np.isfinite(gyro), -1)
                                    & np.all(np.isfinite(accel), -1)), 3, kind)
    bad = (kind > 0) & mask
    if bad.any():
        idx = np.argwhere(bad)
        msgs = []
        for i in idx[:5]:
            what = _BAD_KIND[int(kind[tuple(i)])]
            where = tuple(int(v) for v in i) if len(i) > 1 else int(i[0])
            msgs.append(f"sample {where}: {what}")
        more = f" (and {len(idx) - 5} more)" if len(idx) > 5 else ""
        raise DataError("preintegrate: bad IMU samples: " + "; ".join(msgs) + more)
    n_used = np.sum(mask, axis=-1)
    if np.any(n_used == 0):
        raise DataError(
            "preintegrate: empty interval (no unmasked samples)"
            + ("" if n_used.ndim == 0 else f" in windows {np.argwhere(n_used == 0).ravel()[:10]}")
        )


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


def preintegrate(
    dt,
    gyro,
    accel,
    bias_gyro=None,
    bias_accel=None,
    *,
    mask=None,
    noise: ImuNoise = EUROC_ADIS16448,
    offset=None,
    scheme: str = "tangent",
    bias_covariance: bool = False,
    covariance: str = "auto",
    unroll: int = 1,
) -> Preintegrated:
    """Preintegrate IMU samples (GTSAM's ``integrateMeasurement`` semantics) with ``lax.scan``.

    Args:
        dt: (..., N) seconds each sample is held for.
        gyro: (..., N, 3) angular rate in the IMU (body) frame, rad/s.
        accel: (..., N, 3) specific force in the IMU frame, m/s^2.
        bias_gyro, bias_accel: (..., 3) or (3,) biases subtracted from every sample (the
            linearisation point of the bias Jacobians); zeros by default.
        mask: (..., N) bool, ``False`` for padding samples (skipped exactly); all ``True``
            by default. Pad ``dt``, ``gyro``, ``accel`` with any finite values.
        noise: :class:`~uavcal_jax.imu.noise.ImuNoise` (default: EuRoC's ADIS16448).
        offset: optional (..., 6) or (6,) additive IMU offset (gyro xyz, accel xyz) to remove
            from the samples before integrating (``sample - offset``); differentiable.
        scheme: ``"tangent"`` (GTSAM's, default) or ``"manifold"`` (Forster Euler).
        bias_covariance: also propagate the bias random walk: ``cov`` becomes 15x15.
        covariance: ``"closed"`` (isotropic closed form), ``"recursive"`` (GTSAM's per-sample
            propagation) or ``"auto"`` (closed when possible); see the module docstring.
        unroll: ``lax.scan`` unroll factor (a speed knob; results do not depend on it).

    Returns:
        :class:`Preintegrated` with the leading batch axes of the inputs. Differentiable with
        respect to ``dt``, the samples, the biases, the offset and the noise densities;
        ``jax.vmap`` over windows gives the same numbers as a loop.

    Raises:
        DataError: called eagerly with concrete arrays, on shape mismatches, non-finite
            samples/biases/offset, ``dt <= 0`` on an unmasked sample, or an empty interval.
            Under tracing the result is flagged (``valid == False``) instead.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    isotropic = all(np.ndim(x) == 0 for x in (noise.gyro_noise_density, noise.accel_noise_density))
    if covariance == "auto":
        covariance = "closed" if (isotropic and not bias_covariance) else "recursive"
    if covariance not in ("closed", "recursive"):
        raise ValueError(f"covariance must be 'auto', 'closed' or 'recursive', got {covariance!r}")
    if covariance == "closed" and (bias_covariance or not isotropic):
        raise ValueError("the closed-form covariance needs scalar (isotropic) noise densities "
                         "and bias_covariance=False; use covariance='recursive'")

    traced = _is_traced(dt, gyro, accel, bias_gyro, bias_accel, mask, offset, noise)
    dt, gyro, accel = jnp.asarray(dt), jnp.asarray(gyro), jnp.asarray(accel)
    dtype = _float_dtype(dt, gyro, accel)
    dt, gyro, accel = dt.astype(dtype), gyro.astype(dtype), accel.astype(dtype)
    mask = jnp.ones(dt.shape, bool) if mask is None else jnp.asarray(mask, bool)
    _check_shapes(dt, gyro, accel, mask)
    batch = dt.shape[:-1]
    bg = jnp.zeros(3, dtype) if bias_gyro is None else jnp.asarray(bias_gyro, dtype)
    ba = jnp.zeros(3, dtype) if bias_accel is None else jnp.asarray(bias_accel, dtype)
    off = jnp.zeros(6, dtype) if offset is None else jnp.asarray(offset, dtype)
    bg = jnp.broadcast_to(bg, batch + (3,))
    ba = jnp.broadcast_to(ba, batch + (3,))
    off = jnp.broadcast_to(off, batch + (6,))
    if not traced:
        _eager_check(dt, gyro, accel, mask, bg, ba, off)
    return _preintegrate(dt, gyro, accel, bg, ba, mask, off, noise, scheme=scheme,
                         covariance=covariance, bias_covariance=bias_covariance, unroll=unroll)


@functools.partial(jax.jit, static_argnames=("scheme", "covariance", "bias_covariance", "unroll"))
def _preintegrate(dt, gyro, accel, bg, ba, mask, off, noise, *, scheme, covariance,
                  bias_covariance, unroll) -> Preintegrated:
    dtype = dt.dtype
    bias_ok = (jnp.all(jnp.isfinite(bg), -1) & jnp.all(jnp.isfinite(ba), -1)
               & jnp.all(jnp.isfinite(off), -1))
    ok = _sample_ok(dt, gyro, accel)
    use = ok & mask
    bad = ~ok & mask
    n_used = jnp.sum(use, axis=-1, dtype=jnp.int32)
    use = use & bias_ok[..., None]
    # hold time and the bias- and offset-corrected gyro and accel axes, (..., N) each, with
    # unused samples zeroed (hold time 0 makes a step an exact no-op)
    zero = jnp.zeros((), dtype)
    cg, ca = bg + off[..., :3], ba + off[..., 3:]
    comps = ((jnp.where(use, dt, zero),)
             + tuple(jnp.where(use, gyro[..., i] - cg[..., i, None], zero) for i in range(3))
             + tuple(jnp.where(use, accel[..., i] - ca[..., i, None], zero) for i in range(3)))

    var = noise.variances(dtype)
    n_cov = 15 if bias_covariance else 9
    if covariance == "closed":
        k = _closed.run(comps, var, scheme, unroll)
    else:
        k = _recursive.run(comps, var, scheme, n_cov, unroll)

    p, v = k["p"], k["v"]
    if scheme == "tangent":
        theta = k["rot"]
        delta_R = so3.exp(theta)
        d_theta_d_bg = k["Hr"]
        d_R_d_bg = so3.right_jacobian(theta) @ d_theta_d_bg
    else:
        delta_R = k["rot"]
        theta = so3.log(delta_R)
        d_R_d_bg = k["Hr"]
        d_theta_d_bg = so3.right_jacobian_inv(theta) @ d_R_d_bg

    # internal order (rot, p, v[, bg, ba]) -> output (rot, v, p[, bg, ba])
    perm = np.array([0, 1, 2, 6, 7, 8, 3, 4, 5] + ([9, 10, 11, 12, 13, 14] if n_cov == 15 else []))
    cov = k["cov"][..., perm[:, None], perm[None, :]]
    delta_t = k["t"]
    qb = jnp.concatenate([jnp.stack(var["gyro_rw"], -1), jnp.stack(var["accel_rw"], -1)], -1)
    cov_bias = (qb * delta_t[..., None])[..., :, None] * jnp.eye(6, dtype=dtype)

    valid = ~jnp.any(bad, axis=-1) & (n_used > 0) & bias_ok
    finite = (
        jnp.all(jnp.isfinite(delta_R), (-2, -1))
        & jnp.all(jnp.isfinite(p), -1)
        & jnp.all(jnp.isfinite(v), -1)
        & jnp.all(jnp.isfinite(cov), (-2, -1))
    )
    valid = valid & finite
    if scheme == "tangent":
        valid = valid & (jnp.sum(theta * theta, axis=-1) < THETA_LIMIT**2)

    return Preintegrated(
        delta_R=delta_R, delta_v=v, delta_p=p, delta_t=delta_t, theta=theta,
        d_R_d_bg=d_R_d_bg, d_theta_d_bg=d_theta_d_bg, d_v_d_bg=k["Hv"], d_v_d_ba=k["Hva"],
        d_p_d_bg=k["Hp"], d_p_d_ba=k["Hpa"], cov=cov, cov_bias=cov_bias, bias_gyro=bg,
        bias_accel=ba, valid=valid, n_samples=n_used, scheme=scheme,
    )


def bias_correct(pim: Preintegrated, bias_gyro=None, bias_accel=None):
    """First-order bias correction of the deltas (Forster et al. eq. 44; RPEOD eq. 5).

    Returns ``(delta_R, delta_v, delta_p)`` for new biases (default: the integration biases,
    i.e. no correction). The tangent scheme corrects ``theta`` linearly and maps it through
    ``exp`` (GTSAM's ``biasCorrectedDelta``); the manifold scheme right-multiplies
    ``exp(d_R_d_bg @ dbg)`` (Forster's).
    """
    dbg = (jnp.zeros_like(pim.bias_gyro) if bias_gyro is None
           else jnp.asarray(bias_gyro, pim.bias_gyro.dtype) - pim.bias_gyro)
    dba = (jnp.zeros_like(pim.bias_accel) if bias_accel is None
           else jnp.asarray(bias_accel, pim.bias_accel.dtype) - pim.bias_accel)

    def mv(m, x):
        return jnp.einsum("...ij,...j->...i", m, x)

    if pim.scheme == "tangent":
        delta_R = so3.exp(pim.theta + mv(pim.d_theta_d_bg, dbg))
    else:
        delta_R = pim.delta_R @ so3.exp(mv(pim.d_R_d_bg, dbg))
    delta_v = pim.delta_v + mv(pim.d_v_d_bg, dbg) + mv(pim.d_v_d_ba, dba)
    delta_p = pim.delta_p + mv(pim.d_p_d_bg, dbg) + mv(pim.d_p_d_ba, dba)
    return delta_R, delta_v, delta_p
