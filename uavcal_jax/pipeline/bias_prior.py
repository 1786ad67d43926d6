"""A learned IMU offset as a prior on the stereo VIO's bias states (Buchanan et al. 2022,
"Deep IMU Bias Inference for Robust Visual-Inertial Odometry with Factor Graphs").

An offset estimator's result (:class:`~uavcal_jax.pipeline.offset_estimate.OffsetEstimate`,
with its sigma) is removed from the IMU before the VIO, and the VIO's prior on the first
keyframe's biases at every (re-)initialisation (:class:`~uavcal_jax.vio.config.
InitialPrior`, by default the sensor's turn-on spread, 0.1 rad/s and 0.3 m/s^2) becomes the
estimate's sigma. The prior is centred on the biases the window opens with: zero at the first
initialisation (the learned offset is removed: the window starts from the learned biases, with
the learned confidence), the last trusted state's after a reset (the estimator coasts from
it); the bias random walk lets the data take over as it comes. It is one factor per
initialisation, carried on by the window's marginalisation, not one per frame: a recording's
estimate is one measurement, and repeating it at every keyframe would count it again and
again.

What it buys shows where vision is not enough: after a visual dropout the VIO coasts on the
IMU with the biases it holds, and re-initialises from the prior.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uavcal_jax.data.sequence import Sequence
from uavcal_jax.pipeline.offset_estimate import OffsetEstimate
from uavcal_jax.vio.config import InitialPrior, VioConfig
from uavcal_jax.vio.run import VioResult, run_vio

__all__ = ["MIN_SIGMA", "prior_from_estimate", "run_vio_with_prior"]

#: The tightest prior taken, gyro rad/s and accel m/s^2: the bias random walk over a
#: recording's seconds moves the sensor's bias by about this much, whatever an estimate says.
MIN_SIGMA = (2e-4, 5e-3)


def prior_from_estimate(estimate: OffsetEstimate,
                        base: InitialPrior = InitialPrior()) -> InitialPrior:  # noqa: B008
    """``base`` with its bias standard deviations taken from ``estimate.sigma`` (per sensor,
    the root mean square over the axes it estimates; never looser than ``base``, never
    tighter than :data:`MIN_SIGMA`); a sensor the estimate does not determine keeps
    ``base``'s.

    Raises:
        ValueError: the estimate has no sigma.
    """
    if estimate.sigma is None:
        raise ValueError("the estimate has no sigma (a model without model.variance)")
    sigma = np.full(6, np.inf)
    sigma[estimate.channel_index] = np.asarray(estimate.sigma, np.float64)
    out = {}
    for name, axes, floor in (("bias_gyro", slice(0, 3), MIN_SIGMA[0]),
                              ("bias_accel", slice(3, 6), MIN_SIGMA[1])):
        rms = float(np.sqrt(np.mean(np.square(sigma[axes]))))
        out[name] = float(np.clip(rms, floor, getattr(base, name))) if np.isfinite(rms) \
            else getattr(base, name)
    return dataclasses.replace(base, **out)


def run_vio_with_prior(sequence: Sequence, estimate: OffsetEstimate,
                       config: VioConfig | None = None, **kwargs) -> VioResult:
    """The VIO over ``sequence`` with ``estimate``'s offset removed from the IMU and its sigma
    as the prior on the biases (:func:`prior_from_estimate`); ``kwargs`` go to
    :func:`~uavcal_jax.vio.run.run_vio`."""
    config = VioConfig() if config is None else config
    config = dataclasses.replace(config, prior=prior_from_estimate(estimate, config.prior))
    return run_vio(sequence, config, imu_offset=estimate.offset, **kwargs)
