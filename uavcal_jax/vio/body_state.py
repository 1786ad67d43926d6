"""The body state at one instant, on the host: the one shape the estimator predicts, solves,
resets to and publishes (:attr:`~uavcal_jax.vio.frame_estimate.FrameEstimate.state`).

Frames: the body is the IMU frame; the world frame is gravity-aligned (z up), its origin and
yaw fixed at initialisation. NumPy float64 throughout; :meth:`BodyState.keyframe` hands it to
the jitted back end as one (unbatched) :class:`~uavcal_jax.vio.window.Keyframes`.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from uavcal_jax.imu import ImuNoise, NavState, Preintegrated, predict
from uavcal_jax.vio.window import ImuSamples, Keyframes
from uavcal_jax.vio.window_ops import preintegrate_padded

__all__ = ["BodyState"]

_predict = jax.jit(predict)


@dataclasses.dataclass(frozen=True, eq=False)
class BodyState:
    """Navigation state and biases of the body at ``t_ns``.

    Attributes:
        t_ns: time, ns.
        rotation: (3, 3) body-to-world rotation.
        position: (3,) m, world.  velocity: (3,) m/s, world.
        bias_gyro: (3,) rad/s.  bias_accel: (3,) m/s^2.
    """

    t_ns: int
    rotation: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray

    @classmethod
    def at_rest(cls, t_ns: int, rotation: np.ndarray) -> BodyState:
        """``rotation`` at the world origin, still, with zero biases (the first start)."""
        return cls(t_ns, rotation, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))

    @classmethod
    def unknown(cls, t_ns: int) -> BodyState:
        """All NaN: what a frame without a pose reports."""
        nan3 = np.full(3, np.nan)
        return cls(t_ns, np.full((3, 3), np.nan), nan3, nan3, nan3, nan3)

    @classmethod
    def from_keyframe(cls, t_ns: int, frames: Keyframes, slot: int | None = None
                      ) -> BodyState:
        """Host copy of one keyframe: ``frames`` without a leading axis, or slot ``slot`` of a
        window's (N,) keyframes. ``frames`` is on the host already (one ``jax.device_get`` for
        the whole tree: eager device indexing costs a dispatch per leaf)."""
        leaves = (frames.rotation, frames.position, frames.velocity, frames.bias_gyro,
                  frames.bias_accel)
        if slot is not None:
            leaves = tuple(x[slot] for x in leaves)
        return cls(t_ns, *(np.array(x) for x in leaves))

    def keyframe(self) -> Keyframes:
        """The state as one keyframe for the window's jitted edits."""
        # NumPy leaves: jitted callees convert them in one go (an eager jnp.asarray per leaf
        # costs a dispatch each)
        return Keyframes(self.rotation, self.position, self.velocity, self.bias_gyro,
                         self.bias_accel)

    def hold(self, t_ns: int) -> BodyState:
        """Carried to ``t_ns`` at constant velocity: across an interval the IMU does not cover
        (a gap), the one prediction left."""
        dt = (t_ns - self.t_ns) * 1e-9
        return dataclasses.replace(self, t_ns=t_ns, position=self.position + self.velocity * dt)

    def propagate(self, row: ImuSamples, noise: ImuNoise, t_ns: int
                  ) -> tuple[Preintegrated, BodyState]:
        """``(pim, state at t_ns)``: ``row`` (one padded interval, (S,) leading axis)
        preintegrated at this state's biases, and the prediction through it (biases kept)."""
        pim = preintegrate_padded(row.dt, row.gyro, row.accel, row.mask, self.bias_gyro,
                                  self.bias_accel, noise, row.dt.shape[0])
        out = _predict(NavState(self.rotation, self.position, self.velocity), pim)
        R, p, v = (np.asarray(x) for x in (out.rotation, out.position, out.velocity))
        return pim, BodyState(t_ns, R, p, v, self.bias_gyro.copy(), self.bias_accel.copy())
