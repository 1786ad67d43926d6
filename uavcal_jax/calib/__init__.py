"""The transformer IMU self-calibrator of Avola et al. (Sensors 2023, 23, 2655).

Modules: :mod:`~uavcal_jax.calib.config` (every option of a run, one typed root, paper
defaults), :mod:`~uavcal_jax.calib.presets` (named runs: paper, small, shipped; a run's
configuration from a preset, arguments and ``key=value`` overrides),
:mod:`~uavcal_jax.calib.layers` (transformer encoder/decoder stacks),
:mod:`~uavcal_jax.calib.model` (the network, section 3), :mod:`~uavcal_jax.calib.loss` (eq.
15-18), :mod:`~uavcal_jax.calib.metrics` (eq. 19-23), :mod:`~uavcal_jax.calib.inject`
(offset-injection protocols, eq. 12), :mod:`~uavcal_jax.calib.batch` (window batches to model
inputs), :mod:`~uavcal_jax.calib.inference` (frame-token reuse over a sequence) and
:mod:`~uavcal_jax.calib.train` (jitted steps, vmapped seeds, data parallel),
:mod:`~uavcal_jax.calib.baselines` (the mean-offset and classical least-squares baselines),
:mod:`~uavcal_jax.calib.loop` (epochs, checkpoints, resume, weight export),
:mod:`~uavcal_jax.calib.trials` (validation trials, their run folders, mean ± std over them),
:mod:`~uavcal_jax.calib.schedule` (a time budget spread over many fits),
:mod:`~uavcal_jax.calib.predict` (a sequence's offset from a trained run) and
:mod:`~uavcal_jax.calib.pretrained` (the shipped demo weights). The simulated training sets are
:mod:`uavcal_jax.sim.training_sets` (the calibrator never imports the simulator).
"""

from uavcal_jax.calib.baselines import (
    LeastSquaresConfig,
    least_squares_windows,
    mean_offset,
)
from uavcal_jax.calib.batch import frames_to_model, model_batch
from uavcal_jax.calib.config import (
    CalibConfig,
    CalibRunConfig,
    InjectionConfig,
    LoopConfig,
    LossConfig,
    ModelConfig,
    TrainConfig,
)
from uavcal_jax.calib.inject import (
    ImuStats,
    imu_statistics,
    inject,
    sample_offset,
    training_offsets,
    validation_offsets,
)
from uavcal_jax.calib.loss import calibration_loss, loss_terms
from uavcal_jax.calib.metrics import calibration_metrics, metric_sums, metrics_from_sums
from uavcal_jax.calib.model import Calibrator
from uavcal_jax.calib.train import (
    CalibState,
    create_train_state,
    create_train_states,
    eval_step,
    eval_step_seeds,
    train_step,
    train_step_seeds,
)

__all__ = [
    "CalibConfig",
    "CalibRunConfig",
    "CalibState",
    "Calibrator",
    "ImuStats",
    "InjectionConfig",
    "LeastSquaresConfig",
    "LoopConfig",
    "LossConfig",
    "ModelConfig",
    "TrainConfig",
    "calibration_loss",
    "calibration_metrics",
    "create_train_state",
    "create_train_states",
    "eval_step",
    "eval_step_seeds",
    "frames_to_model",
    "imu_statistics",
    "inject",
    "least_squares_windows",
    "loss_terms",
    "mean_offset",
    "metric_sums",
    "metrics_from_sums",
    "model_batch",
    "sample_offset",
    "train_step",
    "train_step_seeds",
    "training_offsets",
    "validation_offsets",
]
