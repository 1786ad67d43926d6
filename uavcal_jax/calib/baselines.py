"""Baselines for the calibrator's tables: (a) the training-set mean offset; (b) the classical
least-squares constant IMU offset against ground-truth states.

Convention (:mod:`uavcal_jax.imu.offset`): an IMU with offset ``o`` reads ``gyro + o[:3]``
(rad/s), ``accel + o[3:]`` (m/s^2); preintegration biases are subtracted the same way, so the
bias estimated here *is* the offset the calibrator predicts, gyro then accel -- the stream's
whole constant error: ``o + b`` on a stream that already carries a bias ``b`` (a real IMU,
the simulator's turn-on bias; :func:`ground_truth_bias` gives ``b`` where the ground truth
has it).

Least squares: VINS-Mono's ``solveGyroscopeBias`` (initial_aligment.cpp) with ground-truth
rotations for the camera's. Keyframes are ground-truth samples every ``interval`` s; each
consecutive pair preintegrates the IMU over ``[t_i, t_j]``; the residuals are those of
:func:`uavcal_jax.imu.imu_residual` (body = IMU frame, world z up)::

    r_R(bg)     = log(dR(bg)^T R_i^T R_j)
    r_v(bg, ba) = R_i^T (v_j - v_i - g dt) - dv(bg, ba)
    r_p(bg, ba) = R_i^T (p_j - p_i - v_i dt - g dt^2 / 2) - dp(bg, ba)

gyro: Gauss-Newton on ``sum |r_R|^2`` (unweighted, as VINS-Mono; Jacobian ``Jl(r)^-1
d_R_d_bg``), re-preintegrating at each new bias, so the fixed point is the exact minimum of
the nonlinear cost. accel: with the gyro offset fixed to its estimate, linear least squares on
``(r_v, r_p)`` whitened by their propagated covariance (the (v, p) block of
:func:`uavcal_jax.imu.residual_covariance` at zero accel bias, then held fixed); ``dv``,
``dp`` are exactly linear in the accel bias, so one solve is exact. float64 under x64.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.sequence import GroundTruth
from uavcal_jax.data.windows import WindowSet
from uavcal_jax.errors import DataError
from uavcal_jax.geometry import so3
from uavcal_jax.imu.interval import interval_batch, interval_capacity
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise
from uavcal_jax.imu.offset import add_offset
from uavcal_jax.imu.preintegration import SCHEMES, preintegrate
from uavcal_jax.imu.residual import NavState, imu_residual, residual_covariance

__all__ = [
    "KeyframePairs",
    "LeastSquaresConfig",
    "ground_truth_bias",
    "ground_truth_bias_windows",
    "ground_truth_rotations",
    "keyframe_pairs",
    "least_squares_fit",
    "least_squares_windows",
    "mean_offset",
]


def mean_offset(train_offsets, mask=None) -> jax.Array:
    """Mean ``(C,)`` of the training offsets ``(..., C)`` (rad/s, m/s^2) over every leading
    axis; ``mask`` (...) bool excludes rows (padding)."""
    o = jnp.asarray(train_offsets).reshape(-1, jnp.shape(train_offsets)[-1])
    w = jnp.ones(o.shape[0], o.dtype) if mask is None else jnp.asarray(mask, o.dtype).reshape(-1)
    return jnp.sum(o * w[:, None], axis=0) / jnp.sum(w)


@dataclasses.dataclass(frozen=True)
class LeastSquaresConfig:
    """Keyframe pairs and solver of the least-squares baseline.

    Attributes:
        interval: seconds between keyframes (VINS-Mono's keyframes: 0.1-0.5 s).
        max_gap: pairs longer than ``max_gap * interval`` (ground-truth gaps) are dropped.
        min_pairs: fewer usable pairs than this in a span is a :class:`DataError`.
        iterations: gyro Gauss-Newton iterations, each a re-preintegration (2-3 converge to
            rounding for real bias sizes).
        whiten: weight the accel rows by their propagated covariance (else unweighted).
        scheme: preintegration scheme (:data:`uavcal_jax.imu.SCHEMES`).
        chunk: windows solved per vmapped call by :func:`least_squares_windows` (memory only).
    """

    interval: float = 0.25
    max_gap: float = 1.5
    min_pairs: int = 4
    iterations: int = 3
    whiten: bool = True
    scheme: str = "tangent"
    chunk: int = 32

    def __post_init__(self) -> None:
        if not (self.interval > 0 and self.max_gap >= 1.0 and self.min_pairs >= 1
                and self.iterations >= 1 and self.chunk >= 1):
            raise ValueError(f"bad least-squares config: {self} (interval > 0, max_gap >= 1, "
                             "min_pairs, iterations, chunk >= 1)")
        if self.scheme not in SCHEMES:
            raise ValueError(f"scheme must be one of {SCHEMES}, got {self.scheme!r}")


@dataclasses.dataclass(frozen=True)
class KeyframePairs:
    """Consecutive ground-truth keyframes and the IMU samples between them (a pytree;
    leading axes ``...`` allowed, e.g. windows).

    Attributes:
        dt, gyro, accel, mask: (..., P, N[, 3]) interval samples (see
            :class:`uavcal_jax.imu.ImuInterval`), s, rad/s, m/s^2, IMU frame.
        pair_mask: (..., P) bool, ``False`` on padding pairs.
        state_i, state_j: :class:`uavcal_jax.imu.NavState` (..., P) ground truth at the
            pair's ends: body-to-world rotation, world position (m) and velocity (m/s).
    """

    dt: jax.Array
    gyro: jax.Array
    accel: jax.Array
    mask: jax.Array
    pair_mask: jax.Array
    state_i: NavState
    state_j: NavState


jax.tree_util.register_dataclass(
    KeyframePairs, data_fields=[f.name for f in dataclasses.fields(KeyframePairs)],
    meta_fields=[])

#: Padded shapes are rounded up to these steps, so spans of similar length share one compile.
_PAIRS_STEP = 16
_CAPACITY_STEP = 32


def _keyframe_index(gt_t_ns, lo: int, hi: int, config: LeastSquaresConfig) -> np.ndarray:
    """(P, 2) ground-truth indices of consecutive keyframes inside ``[lo, hi]`` (ns)."""
    step = int(round(config.interval * 1e9))
    first = int(np.searchsorted(gt_t_ns, lo, side="left"))
    last = int(np.searchsorted(gt_t_ns, hi, side="right")) - 1
    if last - first < 1:
        return np.zeros((0, 2), np.int64)
    targets = gt_t_ns[first] + step * np.arange((gt_t_ns[last] - gt_t_ns[first]) // step + 1)
    idx = np.unique(np.clip(np.searchsorted(gt_t_ns, targets, side="left"), first, last))
    pairs = np.stack([idx[:-1], idx[1:]], axis=1)
    span = gt_t_ns[pairs[:, 1]] - gt_t_ns[pairs[:, 0]]
    return pairs[span <= config.max_gap * step]


def keyframe_pairs(imu_t_ns, gyro, accel, gt_t_ns, gt_rotation, gt_position, gt_velocity,
                   config: LeastSquaresConfig = LeastSquaresConfig(), *, span=None,
                   offset=None, capacity: int | None = None, n_pairs: int | None = None,
                   where=None) -> KeyframePairs:
    """Keyframe pairs of one stream (NumPy float64, validated eagerly).

    Args:
        imu_t_ns: (N,) int64 ns; gyro, accel: (N, 3) rad/s, m/s^2 in the IMU (body) frame.
        gt_t_ns: (M,) int64 ns; gt_rotation (M, 3, 3) body-to-world; gt_position (M, 3) m and
            gt_velocity (M, 3) m/s, world frame (z up).
        span: optional ``(t_start_ns, t_end_ns)`` to use only that part (a window).
        offset: optional (6,) offset added to the samples first (:func:`imu.add_offset`).
        capacity, n_pairs: pad to at least these sizes (to stack windows); both are rounded
            up to a step (16 pairs, 32 samples) so similar spans share one compile.
        where: name used in error messages.

    Raises:
        DataError: fewer than ``config.min_pairs`` pairs, or bad samples inside them.
    """
    imu_t_ns, gt_t_ns = np.asarray(imu_t_ns, np.int64), np.asarray(gt_t_ns, np.int64)
    gyro, accel = np.asarray(gyro, np.float64), np.asarray(accel, np.float64)
    if offset is not None:
        gyro, accel = (np.asarray(x, np.float64) for x in add_offset(gyro, accel, offset))
    span = (imu_t_ns[0], imu_t_ns[-1]) if span is None else span
    lo, hi = max(int(imu_t_ns[0]), int(span[0])), min(int(imu_t_ns[-1]), int(span[1]))
    pairs = _keyframe_index(gt_t_ns, lo, hi, config)
    n = len(pairs)
    if n < config.min_pairs:
        raise DataError(f"least-squares offset: {n} keyframe pairs of {config.interval:g} s "
                        f"with ground truth in [{lo * 1e-9:.3f}, {hi * 1e-9:.3f}] s, need "
                        f"{config.min_pairs}", where)
    starts, ends = gt_t_ns[pairs[:, 0]], gt_t_ns[pairs[:, 1]]
    # cut from the samples around the span only (interval_batch validates what it is given)
    sl = slice(max(int(np.searchsorted(imu_t_ns, starts[0], side="right")) - 1, 0),
               int(np.searchsorted(imu_t_ns, ends[-1], side="left")) + 1)
    need = max(interval_capacity(imu_t_ns[sl], starts, ends), capacity or 0)
    iv = interval_batch(imu_t_ns[sl], gyro[sl], accel[sl], starts, ends,
                        capacity=-(-need // _CAPACITY_STEP) * _CAPACITY_STEP)
    pad = -(-max(n, n_pairs or 0) // _PAIRS_STEP) * _PAIRS_STEP - n

    def padded(x, fill=0.0):
        x = np.asarray(x)
        return np.concatenate([x, np.full((pad,) + x.shape[1:], fill, x.dtype)])

    # a padding pair holds one still sample: preintegrate's eager checks refuse empty
    # intervals, and its weight is zero anyway
    dt, mask = padded(iv.dt), padded(iv.mask, False)
    dt[n:, 0], mask[n:, 0] = config.interval, True
    R, eye = np.asarray(gt_rotation, np.float64), np.broadcast_to(np.eye(3), (pad, 3, 3))
    states = [NavState(np.concatenate([R[pairs[:, c]], eye]),
                       padded(np.asarray(gt_position, np.float64)[pairs[:, c]]),
                       padded(np.asarray(gt_velocity, np.float64)[pairs[:, c]])) for c in (0, 1)]
    return KeyframePairs(dt=dt, gyro=padded(iv.gyro), accel=padded(iv.accel), mask=mask,
                         pair_mask=padded(np.ones(n, bool), False), state_i=states[0],
                         state_j=states[1])


def _sum_normal(w, A, r):
    """``sum_k w_k A_k^T A_k`` and ``sum_k w_k A_k^T r_k`` over the pair axis."""
    return jnp.einsum("p,pki,pkj->ij", w, A, A), jnp.einsum("p,pki,pk->i", w, A, r)


def _rotation_terms(pairs: KeyframePairs, pim):
    """``r_R`` (P, 3) and ``A`` (P, 3, 3) with ``r_R(bg + d) ~= r_R - A d``."""
    r = imu_residual(pairs.state_i, None, pairs.state_j, None, pim)[..., :3]
    # log(exp(a) exp(r)) ~= r + Jl(r)^-1 a, and dR(bg + d) ~= dR exp(d_R_d_bg d)
    return r, so3.right_jacobian_inv(-r) @ pim.d_R_d_bg


@jax.jit
@jax.vmap
def _gyro_step(pairs: KeyframePairs, pim, bg):
    """Gauss-Newton update of one window's gyro bias (3,) from its pairs' preintegration."""
    r, A = _rotation_terms(pairs, pim)
    H, g = _sum_normal(pairs.pair_mask.astype(r.dtype), A, r)
    return bg + jnp.linalg.solve(H, g)


@partial(jax.jit, static_argnames=("whiten",))
@partial(jax.vmap, in_axes=(0, 0, None))
def _accel_solve(pairs: KeyframePairs, pim, whiten: bool):
    """One window's accel bias (3,), its predicted std (6,) and validity, given the
    preintegration at (its gyro estimate, zero accel bias)."""
    w = pairs.pair_mask.astype(pim.delta_v.dtype)
    r_R, A = _rotation_terms(pairs, pim)
    H_g_inv = jnp.linalg.inv(_sum_normal(w, A, r_R)[0])
    cov_res = residual_covariance(pim)
    cov_bg = H_g_inv @ jnp.einsum("p,pki,pkl,plj->ij", w, A, cov_res[..., :3, :3], A) @ H_g_inv

    r_vp = imu_residual(pairs.state_i, None, pairs.state_j, None, pim)[..., 3:9]
    B = jnp.concatenate([pim.d_v_d_ba, pim.d_p_d_ba], axis=-2)  # r(ba) = r_vp - B ba
    C = jnp.concatenate([pim.d_v_d_bg, pim.d_p_d_bg], axis=-2)  # r(bg + e) = r_vp - C e
    eye6 = jnp.eye(6, dtype=w.dtype)
    S = jnp.where(pairs.pair_mask[:, None, None], cov_res[..., 3:9, 3:9], eye6)
    L = jnp.linalg.cholesky(S) if whiten else jnp.broadcast_to(eye6, S.shape)
    tri = jax.vmap(partial(jax.scipy.linalg.solve_triangular, lower=True))
    Bw, Cw, rw = tri(L, B), tri(L, C), tri(L, r_vp[..., None])[..., 0]
    H_a, g_a = _sum_normal(w, Bw, rw)
    H_a_inv = jnp.linalg.inv(H_a)
    K = H_a_inv @ jnp.einsum("p,pki,pkj->ij", w, Bw, Cw)  # d ba / d bg
    cov_ba = H_a_inv if whiten else H_a_inv @ jnp.einsum("p,pki,pkl,plj->ij", w, B, S, B) @ H_a_inv
    cov_ba = cov_ba + K @ cov_bg @ K.T
    std = jnp.sqrt(jnp.concatenate([jnp.diagonal(cov_bg), jnp.diagonal(cov_ba)]))
    return H_a_inv @ g_a, std, jnp.all(pim.valid | ~pairs.pair_mask)


def least_squares_fit(pairs: KeyframePairs, noise: ImuNoise = EUROC_ADIS16448,
                      config: LeastSquaresConfig = LeastSquaresConfig(), where=None
                      ) -> tuple[jax.Array, jax.Array]:
    """Solve keyframe pairs shaped (W, P, ...) (W windows) for their offsets.

    The preintegration runs eagerly on all W * P intervals at once (one compile per padded
    shape, see :func:`keyframe_pairs`); the per-window algebra is vmapped.

    Returns ``offset`` (W, 6), gyro rad/s then accel m/s^2, and ``std`` (W, 6), its standard
    deviation predicted from the white-noise model ``noise`` (the gyro estimate's error is
    carried into the accel part; their correlation and the bias random walk are not).
    Raises :class:`DataError` when a real interval's preintegration is invalid.
    """
    pairs = jax.tree_util.tree_map(jnp.asarray, pairs)
    if pairs.pair_mask.ndim != 2:
        raise ValueError(f"pairs must be (W, P, ...), got pair_mask {pairs.pair_mask.shape}")
    # one leaf type whatever the source (Python floats, NumPy scalars from a sensor.yaml),
    # so every recording hits the same compiled preintegration
    noise = jax.tree_util.tree_map(
        lambda x: float(x) if np.ndim(x) == 0 else np.asarray(x, np.float64), noise)

    def pim_at(bg):
        return preintegrate(pairs.dt, pairs.gyro, pairs.accel, bg[:, None, :], None,
                            mask=pairs.mask, noise=noise, scheme=config.scheme)

    bg = jnp.zeros(pairs.pair_mask.shape[:1] + (3,), pairs.dt.dtype)
    for _ in range(config.iterations):
        bg = _gyro_step(pairs, pim_at(bg), bg)
    ba, std, valid = _accel_solve(pairs, pim_at(bg), config.whiten)
    if not bool(jnp.all(valid)):
        raise DataError("least-squares offset: an interval's preintegration is invalid "
                        "(rotation past the scheme's range: use a shorter interval)", where)
    return jnp.concatenate([bg, ba], axis=-1), std


def ground_truth_rotations(gt: GroundTruth) -> np.ndarray:
    """(M, 3, 3) body-to-world rotations of the ground truth's (w, x, y, z) quaternions."""
    return np.asarray(so3.from_quaternion(jnp.asarray(gt.quaternion)), np.float64)


def _check_ground_truth(gt: GroundTruth | None, where) -> GroundTruth:
    if gt is None or gt.velocity is None:
        raise DataError("the least-squares offset needs ground truth with velocities", where)
    return gt


def _window_spans(ws: WindowSet) -> np.ndarray:
    return np.stack([ws.start_ns, ws.start_ns + int(round(ws.config.duration * 1e9))], axis=1)


def least_squares_windows(ws: WindowSet, ground_truth: GroundTruth, offsets=None,
                          config: LeastSquaresConfig = LeastSquaresConfig(), *,
                          noise: ImuNoise = EUROC_ADIS16448) -> jax.Array:
    """The least-squares offset of every window of ``ws``, ``(n_windows, 6)``.

    Window ``k`` uses the full-rate IMU samples and ground-truth keyframes inside
    ``[start_k, start_k + duration]``; ``offsets`` (n_windows, 6), if given, is injected into
    window ``k``'s samples first (what the calibrator is evaluated on). Windows are padded to
    one shape and solved ``config.chunk`` at a time in one vmapped call. Raises
    :class:`DataError` for a window with fewer than ``config.min_pairs`` keyframe pairs.
    """
    _check_ground_truth(ground_truth, ws.name)
    spans = _window_spans(ws)
    if offsets is not None and np.shape(offsets) != (len(ws), 6):
        raise ValueError(f"offsets must be ({len(ws)}, 6), got {np.shape(offsets)}")
    R = ground_truth_rotations(ground_truth)
    t_gt, t_imu = np.asarray(ground_truth.t_ns, np.int64), np.asarray(ws.imu_t_ns, np.int64)
    # one padded shape for every window, so one compile serves the whole set
    idx = [_keyframe_index(t_gt, max(lo, int(t_imu[0])), min(hi, int(t_imu[-1])), config)
           for lo, hi in spans]
    n_pairs = max(len(i) for i in idx)
    capacity = max(interval_capacity(t_imu, t_gt[i[:, 0]], t_gt[i[:, 1]]) if len(i) else 1
                   for i in idx)

    def one(k):
        return keyframe_pairs(t_imu, ws.gyro, ws.accel, t_gt, R, ground_truth.position,
                              ground_truth.velocity, config, span=spans[k],
                              offset=None if offsets is None else offsets[k],
                              capacity=capacity, n_pairs=n_pairs,
                              where=f"{ws.name}, window {k}")

    out, chunk = [], min(config.chunk, len(ws))
    for c0 in range(0, len(ws), chunk):
        ks = [min(k, len(ws) - 1) for k in range(c0, c0 + chunk)]  # a fixed chunk: one compile
        stacked = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *[one(k) for k in ks])
        out.append(least_squares_fit(stacked, noise, config, where=ws.name)[0])
    return jnp.concatenate(out, axis=0)[:len(ws)]


def ground_truth_bias(ground_truth: GroundTruth, span=None) -> np.ndarray:
    """Mean ground-truth bias over ``span = (t_start_ns, t_end_ns)`` (default: all), (6,)
    gyro rad/s then accel m/s^2 -- the stream's own offset, in the calibrator's convention.
    Raises :class:`DataError` without bias columns or without a sample in ``span``."""
    gt = ground_truth
    if gt.bias_gyro is None or gt.bias_accel is None:
        raise DataError("the ground truth has no bias columns")
    t = np.asarray(gt.t_ns, np.int64)
    keep = np.ones(t.shape, bool) if span is None else (t >= span[0]) & (t <= span[1])
    if not keep.any():
        raise DataError("no ground-truth sample in the span")
    return np.concatenate([np.mean(gt.bias_gyro[keep], 0), np.mean(gt.bias_accel[keep], 0)])


def ground_truth_bias_windows(ws: WindowSet, ground_truth: GroundTruth) -> np.ndarray:
    """:func:`ground_truth_bias` of every window of ``ws``, ``(n_windows, 6)``."""
    return np.stack([ground_truth_bias(ground_truth, s) for s in _window_spans(ws)])
