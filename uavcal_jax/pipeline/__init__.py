"""The composition layer: what needs several task packages (``calib``, ``vio``, ``detect``,
``track``) at once. The only package that imports more than one of them; the commands and
the experiments call it, no task package imports it (the import-linter contracts in
``pyproject.toml``).

Modules, one job each:

* :mod:`~uavcal_jax.pipeline.offset_estimate`: :class:`OffsetEstimate` (what every IMU offset
  estimator returns) and :class:`OffsetMethod` (one estimator, as the registry holds it).
* :mod:`~uavcal_jax.pipeline.offset_estimators`: the registry of estimators by name
  (:data:`METHODS`, :func:`get_method`, :func:`configure_method`).
* :mod:`~uavcal_jax.pipeline.vio_bias`: ``vio-bias``, the median of the stereo VIO's bias
  states over the end of the flight (read from ``uavcal run``'s own VIO pass by default).
* :mod:`~uavcal_jax.pipeline.visual_ls`: ``visual-ls``, VINS-Mono's gyro-bias least squares
  against the front end's visual rotations.
* :mod:`~uavcal_jax.pipeline.motion_inputs`: the calibrator's visual rotations (the
  ``rotation_source`` ``calib`` takes).
* :mod:`~uavcal_jax.pipeline.offset_scores`: estimators scored on recordings whose truth is
  known (issue 20's tables).
* :mod:`~uavcal_jax.pipeline.transformer_offset`: ``transformer``, the trained calibrator of
  Avola et al. (``uavcal_jax.calib``).
* :mod:`~uavcal_jax.pipeline.predict_offset`: a recording's offset by any method, and the one
  function that scores an estimate against the truth (its callers hold the truth).
* :mod:`~uavcal_jax.pipeline.run`: ``uavcal run``: offset, VIO + detector, target, set-points.
* :mod:`~uavcal_jax.pipeline.run_config`: ``RunConfig``, the run's settings (``--set``).
* :mod:`~uavcal_jax.pipeline.detectors`: ``Detector``; the trained and the label-box ones.
* :mod:`~uavcal_jax.pipeline.tracker`: the online target stage, one frame at a time
  (association, the followed target, localisation (:mod:`~uavcal_jax.pipeline.tracker_locate`),
  heading, filter and follow set-point).
* :mod:`~uavcal_jax.pipeline.targets`: the tracker folded over a recording (``uavcal run``).
* :mod:`~uavcal_jax.pipeline.closed_loop`: the drone flies the tracker's set-points in the
  simulator (:mod:`~uavcal_jax.pipeline.closed_loop_world`,
  :mod:`~uavcal_jax.pipeline.closed_loop_metrics`).
* :mod:`~uavcal_jax.pipeline.run_metrics`: the run against the truth, follow figures, timings.
* :mod:`~uavcal_jax.pipeline.run_outputs`: the output folder's files and ``metrics.json``.
* :mod:`~uavcal_jax.pipeline.drift`: the long-flight drift runs (dead reckoning and the VIO,
  per offset correction) of ``experiments/drift_long_flight.py``.
* :mod:`~uavcal_jax.pipeline.drift_metrics`: their final-position error and error against
  distance travelled.

No estimator sees the ground truth: :func:`~uavcal_jax.pipeline.predict_offset.predict_offset`
hands it the recording (read once, by the caller) without one; the caller scores the estimate
(:func:`~uavcal_jax.pipeline.predict_offset.score`) only once it is made.
"""
