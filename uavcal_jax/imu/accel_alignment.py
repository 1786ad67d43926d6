"""The accelerometer's constant bias from a visual trajectory: a batch linear alignment.

A sliding-window VIO trades the accelerometer bias across gravity against its own tilt: the
two are told apart only by rotating the bias in the world frame, which takes turns spread over
many seconds, longer than its window remembers (on the demo's 12 s flight its bias states
were still off by 0.11 and 0.13 m/s^2 on the two horizontal channels). Over the whole flight
at once it is a linear least squares, VINS-Mono's visual-inertial alignment
(``LinearAlignment`` and ``RefineGravity``) with the accelerometer bias added (as ORB-SLAM3's
inertial-only optimisation has it), the scale known from stereo:

for consecutive nodes ``i -> j`` (poses of the trajectory ``node_spacing_s`` apart) with the
IMU preintegrated between them (``delta_p``, ``delta_v``, their Jacobians ``J`` on the
accelerometer bias ``b``; gyro bias given),

    p_j - p_i - R_i delta_p = v_i T + g T^2 / 2 + R_i J_p b
          R_i delta_v       = v_j - v_i - g T - R_i J_v b

unknowns: every node's velocity, gravity ``g`` per segment (its norm fixed at
:data:`~uavcal_jax.geometry.frames.GRAVITY_W`'s, two tangent directions refined as
``RefineGravity`` does) and ``b``. The positions come from the trajectory (vision fixes them and
their scale); the rotations ``R_i`` are the segment's first pose chained with the gyro's
preintegrated rotations: the relative rotations of a bias-corrected gyro are far better than a
VIO's, whose tilt wanders with its bias estimate (0.07 m/s^2 of error with the VIO's own
rotations on the demo flight, 0.018 chained). A segment restarts at every gap in the
trajectory and after ``segment_s`` (the gyro's residual bias drifts the chain: 1e-4 rad/s over
60 s tilts it 0.006 rad, 0.06 m/s^2 of gravity); each has its own gravity direction, which
also absorbs the trajectory's tilt. Segments should be long: the bias across gravity is seen
only through the turns within one (on the demo's seed-2 flight, 12 s cut at 10 s left the
error at 0.14 m/s^2 on one channel, against 0.015 uncut).

A flight that hardly turns cannot tell the bias across gravity from the tilt: the normal
equations are near singular in that direction and the least squares answers with noise (on
a 12 s flight with 15 degrees of yaw: 0.97 m/s^2 of error on a truth of 0.003). So the bias
has a zero-mean prior, the sensor's turn-on spread ``prior_std``, weighed against the data
with the residuals' own scale, inflated by ``error_inflation`` because a VIO's position errors
are correlated over seconds, not white (on four demo flights the normal equations'
standard deviation was 3-6 times below the error); where the flight turned, the data
outweighs the prior by one or two orders of magnitude.

Frames: the trajectory's world frame (z up, as the VIO's), the body frame the IMU's. Units m,
s, rad, m/s^2.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from uavcal_jax.errors import DataError
from uavcal_jax.geometry.frames import GRAVITY_W
from uavcal_jax.imu.interval import interval_batch
from uavcal_jax.imu.noise import EUROC_ADIS16448, ImuNoise
from uavcal_jax.imu.preintegration import preintegrate

__all__ = ["AccelAlignment", "align_accel_bias", "pick_nodes"]

#: Fewest intervals a segment must hold to enter the solve (fewer cannot separate its gravity
#: from the bias).
MIN_SEGMENT_INTERVALS = 4


@dataclasses.dataclass(frozen=True)
class AccelAlignment:
    """Result of :func:`align_accel_bias`.

    Attributes:
        bias_accel: (3,) the accelerometer's constant bias, IMU frame, m/s^2.
        gravity: (S, 3) each segment's gravity in the trajectory's world frame, m/s^2.
        nodes: (N,) indices into the trajectory of the nodes used.
        segments: S.
        residual_rms: RMS of the whitened residuals at the solution (about 1 when the noise
            model fits).
        bias_std: (3,) m/s^2, the standard deviation of ``bias_accel`` from the normal
            equations with the prior, scaled by ``residual_rms`` times ``error_inflation``
            (near ``prior_std`` where the flight did not turn enough to tell that direction
            from the tilt).
    """

    bias_accel: np.ndarray
    gravity: np.ndarray
    nodes: np.ndarray
    segments: int
    residual_rms: float
    bias_std: np.ndarray


def pick_nodes(t_ns: np.ndarray, spacing_s: float, segment_s: float) -> list[np.ndarray]:
    """Segments of node indices into ``t_ns`` ((N,) int ns, increasing): nodes at least
    ``spacing_s`` apart; a segment ends after ``segment_s`` or where two poses lie more than
    twice ``spacing_s`` apart (a gap: lost tracking, a reset)."""
    t = np.asarray(t_ns, np.int64) * 1e-9
    segments, current, seg_start = [], [], None
    for i, ti in enumerate(t):
        if current and ti - t[current[-1]] > 2.0 * spacing_s:
            segments.append(current)
            current, seg_start = [], None
        if not current:
            current, seg_start = [i], ti
        elif ti - t[current[-1]] >= spacing_s - 1e-9:
            current.append(i)
            if ti - seg_start >= segment_s:
                segments.append(current)
                current, seg_start = [i], ti  # the next segment starts at this node
    if current:
        segments.append(current)
    return [np.asarray(s) for s in segments if len(s) > MIN_SEGMENT_INTERVALS]


def _tangent_basis(g: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal directions perpendicular to ``g``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(g[0]) < 0.9 * np.linalg.norm(g) else \
        np.array([0.0, 1.0, 0.0])
    b1 = np.cross(g, a)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(g / np.linalg.norm(g), b1)
    return np.stack([b1, b2], axis=1)


def align_accel_bias(t_ns, position, rotation, imu_t_ns, gyro, accel, bias_gyro, *,
                     node_spacing_s: float = 0.5, segment_s: float = 60.0,
                     position_sigma: float = 0.003, prior_std: float = 0.1,
                     error_inflation: float = 5.0, noise: ImuNoise = EUROC_ADIS16448,
                     iterations: int = 4) -> AccelAlignment:
    """The accelerometer bias that best explains a trajectory with the IMU (module docstring).

    Args:
        t_ns: (M,) int ns, increasing: the trajectory's poses (well-tracked ones only).
        position: (M, 3) m, world frame.  rotation: (M, 3, 3) body (IMU) to world.
        imu_t_ns: (K,) int ns; gyro, accel: (K, 3) rad/s, m/s^2 (the IMU stream, offset
            included: the bias found is the whole constant error).
        bias_gyro: (3,) rad/s, removed from the gyro before integrating.
        node_spacing_s: seconds between nodes (a longer one divides the positions' noise by
            its square).  segment_s: seconds a rotation chain lasts.
        position_sigma: m, the noise of one position (relative, between nearby nodes).
        prior_std: m/s^2, the bias's zero-mean prior per axis (module docstring).
        error_inflation: how much the residuals' scale understates the estimate's error.
        noise: the IMU noise model (the residuals' weights).
        iterations: gravity refinements.

    Raises:
        DataError: too few poses (no segment of :data:`MIN_SEGMENT_INTERVALS` intervals).
    """
    t_ns = np.asarray(t_ns, np.int64)
    position = np.asarray(position, np.float64)
    rotation = np.asarray(rotation, np.float64)
    segments = pick_nodes(t_ns, node_spacing_s, segment_s)
    if not segments:
        raise DataError(f"the trajectory's {len(t_ns)} poses hold no stretch of "
                        f"{MIN_SEGMENT_INTERVALS + 1} nodes {node_spacing_s} s apart: "
                        "too short to align the accelerometer")
    starts = np.concatenate([t_ns[s[:-1]] for s in segments])
    ends = np.concatenate([t_ns[s[1:]] for s in segments])
    batch = interval_batch(np.asarray(imu_t_ns, np.int64), np.asarray(gyro, np.float64),
                           np.asarray(accel, np.float64), starts, ends)
    m = len(starts)
    pim = preintegrate(batch.dt, batch.gyro, batch.accel, np.tile(bias_gyro, (m, 1)),
                       np.zeros((m, 3)), mask=batch.mask, noise=noise)
    delta_r, delta_v, delta_p = (np.asarray(x, np.float64) for x in
                                 (pim.delta_R, pim.delta_v, pim.delta_p))
    jac_v, jac_p = np.asarray(pim.d_v_d_ba), np.asarray(pim.d_p_d_ba)
    dt = np.asarray(pim.delta_t, np.float64)
    cov = np.asarray(pim.cov, np.float64)
    sigma_v = np.sqrt(cov[:, 3:6, 3:6].trace(axis1=1, axis2=2) / 3.0)
    sigma_p = np.sqrt(cov[:, 6:9, 6:9].trace(axis1=1, axis2=2) / 3.0 + 2.0 * position_sigma ** 2)

    # per interval: its segment, its node columns, the chained rotation at its start
    seg_of, node_i, node_j, r_start = [], [], [], []
    k = n_nodes = 0
    for s, nodes in enumerate(segments):
        r = rotation[nodes[0]]
        for a in range(len(nodes) - 1):
            seg_of.append(s)
            node_i.append(n_nodes + a)
            node_j.append(n_nodes + a + 1)
            r_start.append(r)
            r = r @ delta_r[k]
            k += 1
        n_nodes += len(nodes)
    r_start = np.stack(r_start)
    n_seg = len(segments)
    p_i = np.concatenate([position[s[:-1]] for s in segments])
    p_j = np.concatenate([position[s[1:]] for s in segments])

    g_norm = float(np.linalg.norm(GRAVITY_W))
    gravity = np.tile(np.asarray(GRAVITY_W, np.float64), (n_seg, 1))
    n_cols = 3 * n_nodes + 2 * n_seg + 3
    col_g, col_b = 3 * n_nodes, 3 * n_nodes + 2 * n_seg
    eye = np.eye(3)
    prior = None  # the first solve sets the residuals' scale
    for _ in range(max(2, iterations)):
        basis = np.stack([_tangent_basis(g) for g in gravity])  # (S, 3, 2)
        rows, cols, vals, rhs = [], [], [], []

        def put(r0, c0, block, _rows=rows, _cols=cols, _vals=vals):
            rr, cc = np.nonzero(np.ones_like(block, bool))
            _rows.append(r0 + rr)
            _cols.append(c0 + cc)
            _vals.append(block[rr, cc])

        for q in range(m):
            s, w_p, w_v, t = seg_of[q], 1.0 / sigma_p[q], 1.0 / sigma_v[q], dt[q]
            r0 = 6 * q
            # position row: v_i T + (g0 + B x) T^2/2 + R J_p b = p_j - p_i - R dp
            put(r0, 3 * node_i[q], w_p * t * eye)
            put(r0, col_g + 2 * s, w_p * 0.5 * t * t * basis[s])
            put(r0, col_b, w_p * r_start[q] @ jac_p[q])
            rhs.append(w_p * (p_j[q] - p_i[q] - r_start[q] @ delta_p[q]
                              - 0.5 * t * t * gravity[s]))
            # velocity row: v_j - v_i - (g0 + B x) T - R J_v b = R dv
            put(r0 + 3, 3 * node_j[q], w_v * eye)
            put(r0 + 3, 3 * node_i[q], -w_v * eye)
            put(r0 + 3, col_g + 2 * s, -w_v * t * basis[s])
            put(r0 + 3, col_b, -w_v * r_start[q] @ jac_v[q])
            rhs.append(w_v * (r_start[q] @ delta_v[q] + t * gravity[s]))
        a = scipy.sparse.csr_matrix((np.concatenate(vals),
                                     (np.concatenate(rows), np.concatenate(cols))),
                                    shape=(6 * m, n_cols))
        y = np.concatenate(rhs)
        normal = a.T @ a
        if prior is not None:
            normal = normal + prior
        normal = normal.tocsc()
        x = scipy.sparse.linalg.spsolve(normal, a.T @ y)
        tangent = x[col_g:col_b].reshape(n_seg, 2)
        gravity = gravity + np.einsum("sij,sj->si", basis, tangent)
        gravity *= g_norm / np.linalg.norm(gravity, axis=1, keepdims=True)
        residual = a @ x - y
        rms = float(np.sqrt(np.mean(residual ** 2)))
        # the prior in the data's units: the residuals' scale, inflated (module docstring)
        weight = (rms * error_inflation / prior_std) ** 2
        prior = scipy.sparse.diags(np.r_[np.zeros(col_b), np.full(3, weight)]).tocsr()
    unit = np.zeros((n_cols, 3))
    unit[col_b:, :] = np.eye(3)
    cov_b = np.asarray(scipy.sparse.linalg.spsolve(normal, unit))[col_b:] * (
        rms * error_inflation) ** 2
    return AccelAlignment(bias_accel=x[col_b:], gravity=gravity,
                          nodes=np.concatenate(segments), segments=n_seg, residual_rms=rms,
                          bias_std=np.sqrt(np.diag(cov_b)))
