"""The sliding window: what is estimated, what is measured, and the retraction ``x ⊞ delta``.

Everything is padded to fixed capacities with masks, so a jitted solve compiles once per
``(N, L, M)`` and never per frame:

* ``N`` keyframe slots (:attr:`~uavcal_jax.vio.config.VioConfig.keyframes`), time-ordered; slot
  ``k`` and ``k + 1`` are joined by IMU interval ``k``. Each keyframe has the body (IMU)
  pose in the world frame, the world-frame velocity and the two biases: 15 tangent
  dimensions in the order of :data:`ROT`, :data:`POS`, :data:`VEL`, :data:`BG`,
  :data:`BA` (rotation, position, velocity, gyro bias, accel bias).
* ``L`` landmark slots: inverse depth (1/m, the z-depth of the point in its anchor camera)
  in the anchor keyframe's left camera (camera 0), where the landmark was first observed,
  and that observation's undistorted normalised coordinates (the bearing ``(x, y, 1)``, as
  VINS-Fusion's ``pts_i``). One tangent dimension each.
* ``M`` observation slots: (keyframe, landmark, camera 0/1, undistorted normalised ``xy``).
  The anchoring observation itself is not an observation slot (its residual is identically
  zero); the right camera in the anchor frame is (stereo), as are later frames in both.

:class:`WindowState` holds the variables (keyframes and inverse depths); :class:`WindowProblem`
holds the measurements (landmark anchors, observations, IMU intervals, the marginalisation
prior) and the masks of used slots. The split keeps the solver's unknowns one pytree that
``retract`` acts on.

Retraction: ``R ⊞ d = R exp(d_rot)`` (right perturbation, as GTSAM and VINS-Fusion's
``Qi * deltaQ``), every other component additive; :func:`frame_difference` is its inverse
``x ⊟ x0``, used by the prior.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from uavcal_jax.geometry import so3
from uavcal_jax.imu import Preintegrated
from uavcal_jax.vio.config import CostConfig

__all__ = [
    "BA",
    "BG",
    "FRAME_DIM",
    "POS",
    "POSE_DIM",
    "ROT",
    "VEL",
    "CalibParams",
    "ImuFactors",
    "ImuSamples",
    "Keyframes",
    "Landmarks",
    "Observations",
    "Prior",
    "WindowProblem",
    "WindowState",
    "frame_difference",
    "prior_from_information",
    "retract",
    "retract_frames",
]

#: Tangent dimensions of one keyframe and of its pose part (the first six).
FRAME_DIM = 15
POSE_DIM = 6
ROT = slice(0, 3)
POS = slice(3, 6)
VEL = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)


def _register(cls, meta=()):
    fields = [f.name for f in dataclasses.fields(cls)]
    jax.tree_util.register_dataclass(
        cls, data_fields=[f for f in fields if f not in meta], meta_fields=list(meta))
    return cls


@dataclasses.dataclass(frozen=True)
class Keyframes:
    """Keyframe states (a pytree; leading axis ``N``).

    Attributes:
        rotation: (N, 3, 3) body-to-world rotation.
        position: (N, 3) body origin in the world frame, m.
        velocity: (N, 3) world-frame velocity, m/s.
        bias_gyro: (N, 3) rad/s.  bias_accel: (N, 3) m/s^2.
    """

    rotation: jax.Array
    position: jax.Array
    velocity: jax.Array
    bias_gyro: jax.Array
    bias_accel: jax.Array


@dataclasses.dataclass(frozen=True)
class WindowState:
    """The solver's unknowns: ``frames`` (:class:`Keyframes`) and ``inv_depth`` (L,) 1/m."""

    frames: Keyframes
    inv_depth: jax.Array


@dataclasses.dataclass(frozen=True)
class Landmarks:
    """Landmark anchors (leading axis ``L``).

    Attributes:
        anchor: (L,) int32 keyframe slot of the first observation.
        bearing: (L, 2) undistorted normalised coordinates in the anchor's camera 0.
        mask: (L,) bool, slot in use.
    """

    anchor: jax.Array
    bearing: jax.Array
    mask: jax.Array


@dataclasses.dataclass(frozen=True)
class Observations:
    """Feature observations (leading axis ``M``).

    Attributes:
        frame: (M,) int32 keyframe slot.  landmark: (M,) int32 landmark slot.
        camera: (M,) int32, 0 = left, 1 = right.
        xy: (M, 2) undistorted normalised coordinates ``(x/z, y/z)`` in that camera.
        mask: (M,) bool, slot in use.
    """

    frame: jax.Array
    landmark: jax.Array
    camera: jax.Array
    xy: jax.Array
    mask: jax.Array


@dataclasses.dataclass(frozen=True)
class ImuFactors:
    """IMU intervals between consecutive keyframe slots (leading axis ``N - 1``).

    Attributes:
        pim: :class:`~uavcal_jax.imu.Preintegrated` with batch shape (N - 1,); interval ``k``
            runs from keyframe ``k`` to ``k + 1``.
        mask: (N - 1,) bool, interval in use.
    """

    pim: Preintegrated
    mask: jax.Array


@dataclasses.dataclass(frozen=True)
class ImuSamples:
    """Raw IMU samples of each interval, padded (leading axis ``N - 1``, like ``ImuFactors``;
    one interval's row has no leading axis).

    Kept beside the window so that two intervals can be merged exactly by re-preintegration
    (:func:`~uavcal_jax.vio.marginalize.drop_second_newest`).

    Attributes:
        dt: (N - 1, S) seconds each sample is held for.
        gyro: (N - 1, S, 3) rad/s.  accel: (N - 1, S, 3) m/s^2 (IMU frame, as measured).
        mask: (N - 1, S) bool, sample in use (padding ``False``; any order).
    """

    dt: jax.Array
    gyro: jax.Array
    accel: jax.Array
    mask: jax.Array


@dataclasses.dataclass(frozen=True)
class Prior:
    """Linear marginalisation prior over the keyframe block, as a whitened residual.

    ``r_prior = r + J vec(frames ⊟ lin)`` (VINS-Fusion's ``MarginalizationFactor``: ``J`` and ``r``
    are the ``linearized_jacobians`` / ``linearized_residuals``, ``lin`` the kept block data).
    The linearisation point stays fixed while the window is solved (first-estimate
    Jacobians), so the prior adds no information along unobservable directions.

    Attributes:
        J: (15N, 15N) square-root information; columns of frames outside the prior are zero.
        r: (15N,) residual at the linearisation point.
        lin: :class:`Keyframes` (N,) linearisation point.
        mask: () bool, prior in use.
    """

    J: jax.Array
    r: jax.Array
    lin: Keyframes
    mask: jax.Array


@dataclasses.dataclass(frozen=True)
class WindowProblem:
    """Everything the window cost reads besides the unknowns.

    Attributes:
        frame_mask: (N,) bool, keyframe slot in use.
        landmarks, observations, imu, prior: see their classes.
        config: :class:`~uavcal_jax.vio.config.CostConfig` (static metadata; its
            ``focal_px`` resolved).
    """

    frame_mask: jax.Array
    landmarks: Landmarks
    observations: Observations
    imu: ImuFactors
    prior: Prior
    config: CostConfig

    @property
    def capacities(self) -> tuple[int, int, int]:
        """``(N, L, M)``."""
        return (self.frame_mask.shape[0], self.landmarks.mask.shape[0],
                self.observations.mask.shape[0])


@dataclasses.dataclass(frozen=True)
class CalibParams:
    """Differentiable calibration parameters the window cost depends on (a pytree).

    Attributes:
        imu_offset: (6,) additive IMU offset (gyro rad/s, accel m/s^2) still present in the
            samples the intervals were integrated from (zero when the samples were already
            corrected). It enters the IMU residual through the first-order bias correction
            (``bias + offset`` where the residual reads the bias), not by re-integrating:
            exact in the derivative at the integration bias, and free of a re-integration per
            evaluation. Within one window it is indistinguishable from a bias change except
            through the prior on the biases.
        R_BC: (2, 3, 3) camera-to-body rotations of camera 0 and 1 (EuRoC's ``T_BS``).
        t_BC: (2, 3) camera origins in the body frame, m.
    """

    imu_offset: jax.Array
    R_BC: jax.Array
    t_BC: jax.Array


for _cls in (Keyframes, WindowState, Landmarks, Observations, ImuFactors, ImuSamples, Prior,
             CalibParams):
    _register(_cls)
_register(WindowProblem, meta=("config",))


def retract_frames(frames: Keyframes, delta: jax.Array) -> Keyframes:
    """``frames ⊞ delta`` with ``delta`` (N, 15) in the :data:`ROT` ... :data:`BA` order."""
    return Keyframes(
        rotation=frames.rotation @ so3.exp(delta[..., ROT]),
        position=frames.position + delta[..., POS],
        velocity=frames.velocity + delta[..., VEL],
        bias_gyro=frames.bias_gyro + delta[..., BG],
        bias_accel=frames.bias_accel + delta[..., BA],
    )


def retract(state: WindowState, delta_frames: jax.Array, delta_inv_depth: jax.Array
            ) -> WindowState:
    """``state ⊞ (delta_frames (N, 15), delta_inv_depth (L,))``."""
    return WindowState(retract_frames(state.frames, delta_frames),
                       state.inv_depth + delta_inv_depth)


def frame_difference(frames: Keyframes, lin: Keyframes) -> jax.Array:
    """``frames ⊟ lin``, (N, 15): the ``delta`` with ``lin ⊞ delta == frames``."""
    rot = so3.log(jnp.swapaxes(lin.rotation, -1, -2) @ frames.rotation)
    return jnp.concatenate([rot, frames.position - lin.position,
                            frames.velocity - lin.velocity,
                            frames.bias_gyro - lin.bias_gyro,
                            frames.bias_accel - lin.bias_accel], axis=-1)


def prior_from_information(H: Any, b: Any, lin: Keyframes, eps: float = 1e-8) -> Prior:
    """A :class:`Prior` from the information form ``0.5 d^T H d + b^T d`` (``d = x ⊟ lin``).

    ``H`` (15N, 15N) symmetric positive semi-definite, ``b`` (15N,). As VINS-Fusion's
    ``MarginalizationInfo::marginalize``: ``H = V diag(s) V^T`` keeping ``s > eps``,
    ``J = diag(sqrt(s)) V^T``, ``r = diag(1/sqrt(s)) V^T b``, so that
    ``0.5 |r + J d|^2`` equals the quadratic up to a constant. Directions below ``eps``
    (unobservable) carry no information.
    """
    H = jnp.asarray(H)
    b = jnp.asarray(b)
    H = 0.5 * (H + H.T)
    s, V = jnp.linalg.eigh(H)
    keep = s > eps
    sq = jnp.where(keep, jnp.sqrt(jnp.where(keep, s, 1.0)), 0.0)
    inv_sq = jnp.where(keep, 1.0 / jnp.where(keep, sq, 1.0), 0.0)
    J = sq[:, None] * V.T
    r = inv_sq * (V.T @ b)
    return Prior(J=J, r=r, lin=lin, mask=jnp.asarray(True))
