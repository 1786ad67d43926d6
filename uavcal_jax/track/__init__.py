"""Target tracking: where a detected target is, a filter on its position, follow set-points.

Pure numerics; imports only :mod:`uavcal_jax.geometry` and :mod:`uavcal_jax.imu` from the
project (NumPy, JAX, SciPy, and OpenCV for the stereo path). Modules, one job each:

* :mod:`~uavcal_jax.track.locate`: a box + a depth image + the camera and the pose -> the
  target's world position with a 3x3 covariance, or "not located" with a reason
  (:class:`LocateConfig`). Jitted JAX.
* :mod:`~uavcal_jax.track.depth_box`: a detector's box redrawn around the target the depth
  image shows in it (depth band, height above the ground, the target's size, connectivity;
  :class:`~uavcal_jax.track.depth_box.DepthBoxConfig`). NumPy and OpenCV.
* :mod:`~uavcal_jax.track.box_model`: for a box-shaped target (a car, a person), its centre
  from that front surface at each candidate heading, with how well the box's shape fits.
* :mod:`~uavcal_jax.track.heading`: which candidate heading to believe over time, from the
  boxes' shapes and the target's velocity (a discrete Bayes filter, :class:`HeadingConfig`).
* :mod:`~uavcal_jax.track.stereo`: the same from a stereo pair (``cv2.stereoRectify``, SGBM on
  the box's strip of rows), for recordings without a depth image.
* :mod:`~uavcal_jax.track.filter`: a constant-velocity Kalman filter on the world position
  (continuous white-noise acceleration, chi-square gating, predict while unseen, lost and
  re-initialised), one ``lax.scan`` over frames (:class:`FilterConfig`).
* :mod:`~uavcal_jax.track.associate`: detections -> track ids (Hungarian matching on IoU with
  constant-velocity boxes), online (:class:`Associator`) or over all frames (NumPy).
* :mod:`~uavcal_jax.track.chain`: the target to follow among the tracks, chosen frame by frame
  and continued through identity breaks (:class:`FollowedChain`, NumPy).
* :mod:`~uavcal_jax.track.follow`: follow set-points at a stand-off distance and height,
  facing the target, rate-limited (:class:`FollowConfig`). Jitted JAX.
"""

from uavcal_jax.track.associate import (
    AssociateConfig,
    Associator,
    contained_duplicates,
)
from uavcal_jax.track.filter import (
    LOST,
    PREDICTING,
    STATUS_NAMES,
    TRACKING,
    UNSEEN,
    FilterConfig,
    FilterOutput,
)
from uavcal_jax.track.follow import FollowConfig, Setpoint, follow_step
from uavcal_jax.track.heading import HeadingConfig
from uavcal_jax.track.locate import REASONS, LocateConfig, Located, cut_by_border, locate_box

__all__ = [
    "LOST",
    "PREDICTING",
    "REASONS",
    "STATUS_NAMES",
    "TRACKING",
    "UNSEEN",
    "AssociateConfig",
    "Associator",
    "FilterConfig",
    "FilterOutput",
    "FollowConfig",
    "HeadingConfig",
    "LocateConfig",
    "Located",
    "Setpoint",
    "contained_duplicates",
    "cut_by_border",
    "follow_step",
    "locate_box",
]
