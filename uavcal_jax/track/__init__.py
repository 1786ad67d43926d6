"""Target tracking: where a detected target is, a filter on its position, follow set-points.

Pure numerics; imports only :mod:`uavcal_jax.geometry` and :mod:`uavcal_jax.imu` from the
project (NumPy, JAX, SciPy, and OpenCV for the stereo path). Modules, one job each:

* :mod:`~uavcal_jax.track.locate`: a box + a depth image + the camera and the pose -> the
  target's world position with a 3x3 covariance, or "not located" with a reason
  (:class:`LocateConfig`). Jitted JAX.
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
  constant-velocity boxes), the longest track of a class, and the chain of tracks that
  follows one target through identity breaks (NumPy).
* :mod:`~uavcal_jax.track.follow`: follow set-points at a stand-off distance and height,
  facing the target, rate-limited (:class:`FollowConfig`). Jitted JAX.
"""

from uavcal_jax.track.associate import (
    AssociateConfig,
    assign_track_ids,
    contained_duplicates,
    followed_detections,
    longest_track,
)
from uavcal_jax.track.filter import (
    LOST,
    PREDICTING,
    STATUS_NAMES,
    TRACKING,
    UNSEEN,
    FilterConfig,
    FilterOutput,
    run_filter,
)
from uavcal_jax.track.follow import FollowConfig, Setpoint, follow_setpoints, follow_step
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
    "FilterConfig",
    "FilterOutput",
    "FollowConfig",
    "HeadingConfig",
    "LocateConfig",
    "Located",
    "Setpoint",
    "assign_track_ids",
    "contained_duplicates",
    "cut_by_border",
    "follow_setpoints",
    "follow_step",
    "followed_detections",
    "locate_box",
    "longest_track",
    "run_filter",
]
