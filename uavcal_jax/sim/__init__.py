"""Flight simulator: trajectories, IMU synthesis, rendering, EuRoC ASL output; cached
simulations (:mod:`~uavcal_jax.sim.cache`) and the calibrator's simulated training sets
(:mod:`~uavcal_jax.sim.training_sets`)."""
