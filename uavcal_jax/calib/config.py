"""Configuration of a calibrator run (Avola et al., Sensors 2023, 23, 2655): one typed root.

:class:`CalibRunConfig` is the root of every ``--set`` key and of a run's ``config.json``:

- ``model``, ``loss``, ``injection``, ``train``: the network and its training
  (:class:`CalibConfig`, what the jitted steps carry);
- ``loop``: run control around the steps (:class:`LoopConfig`: early stopping, checkpoints,
  the validation scheme);
- ``window``: how recordings are cut into windows
  (:class:`uavcal_jax.data.windows.WindowConfig`: 10 s windows, 1 s stride, 320x180 frames,
  gray or RGB decoding); the model reads frame size and frames per window from the arrays
  it is given.

Frozen dataclasses; every default is the paper's (section 3, Table 2) unless its docstring
says otherwise. Words: the *protocol* is the offset-injection protocol
(``injection.protocol``: paper, symmetric, physical); the *validation scheme* is how windows
are split into training and validation (``loop.validation``: split, loo, kfold).

A run's ``config.json`` is :func:`uavcal_jax.config.to_dict` of the root plus
:data:`RUN_EXTRAS`; runs written before the root nest the first four sections under
``"calib"`` (:func:`run_layout` reads both). Overrides and JSON: :mod:`uavcal_jax.config`;
named presets: :mod:`uavcal_jax.calib.presets`.

One module over 450 lines, one job: the run's typed settings, each section's field docs
and checks beside its fields (one fact, one place).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields

from uavcal_jax.data.euroc_rig import EUROC_BIAS_SCALE
from uavcal_jax.data.true_offset import LABELS
from uavcal_jax.data.windows import WindowConfig

__all__ = [
    "ACTIVATIONS",
    "FRAME_ENCODER_DTYPES",
    "FRAME_TOKENS",
    "LOSS_UNITS",
    "MONITORS",
    "MOUNTINGS",
    "PROTOCOLS",
    "RUN_EXTRAS",
    "SIGN_TERMS",
    "VALIDATIONS",
    "CalibConfig",
    "CalibRunConfig",
    "InjectionConfig",
    "LoopConfig",
    "LossConfig",
    "ModelConfig",
    "TrainConfig",
    "run_layout",
]

ACTIVATIONS = ("relu", "gelu")
FRAME_TOKENS = ("learned", "first_patch")
FRAME_ENCODER_DTYPES = ("float32", "bfloat16")
#: Closed-form estimates the head can start from (``model.closed_form``).
CLOSED_FORMS = ("none", "window_mean", "rotation_ls", "rotation_window_mean",
                "rotation_alignment")
#: The closed forms that solve the gyro from the rotation residuals (need motion tokens).
ROTATION_CLOSED_FORMS = ("rotation_ls", "rotation_window_mean", "rotation_alignment")
SIGN_TERMS = ("sign", "tanh")
LOSS_UNITS = ("si", "standardized")
#: Offset-injection protocols (``injection.protocol``).
PROTOCOLS = ("paper", "symmetric", "physical")
#: Early-stopping criteria (``loop.monitor``).
MONITORS = ("train", "val")
#: IMU mountings of the training windows (``train.mounting``): the recorded one, or a random
#: one per window (:mod:`uavcal_jax.calib.mounting`).
MOUNTINGS = ("fixed", "random")
#: Validation schemes (``loop.validation``).
VALIDATIONS = ("split", "loo", "kfold")
#: Entries of a run's ``config.json`` beside the settings: derived from the windows
#: (``frames_per_window``, ``frame_shape``) or the command's other inputs (``command``).
RUN_EXTRAS = ("frames_per_window", "frame_shape", "command")


@dataclass(frozen=True)
class ModelConfig:
    """The network (paper section 3, Table 2).

    Attributes:
        d_model: token width ``d`` (256).
        heads: attention heads of every encoder/decoder (8).
        layers: layers of every encoder and of the decoder (2).
        ff_dim: hidden width of every feed-forward block; ``None``: ``4 * d_model`` (the
            PyTorch default the paper's implementation inherits: 1024).
        activation: ``"relu"`` (paper) or ``"gelu"``, everywhere an activation appears.
        dropout: every dropout rate (1 %).
        patch: patch ``(height, width)`` in pixels (64x64); frames are zero-padded at the
            bottom/right to a multiple of it.
        rgb: ``False``: grayscale frames ``(B, n, h, w)``; ``True``: RGB ``(B, n, 3, h, w)``
            through the colour-compression CNN of eq. 1-2.
        imu_channels: IMU values per sample and offsets predicted: 6 (gyro xyz, accel xyz)
            or 3 (a data set with one sensor).
        use_video: ``False`` is the IMU-only variant (no video reducer block).
        frame_token: ``"learned"``: a learned token is prepended to each frame's patch
            tokens and its output row is the frame token (eq. 6); ``"first_patch"``: the
            output row of the first patch is used (the PyTorch peer).
        max_frames: length of the temporal/IMU/fusion positional embeddings; ``None``: the
            frames per window of the batch the model is initialised with.
        norm_first: ``False``: post-norm layers (PyTorch's default, the paper); ``True``:
            pre-norm.
        pixel_scale: multiplies uint8 pixel values before the network (1/255: [0, 1]).
        layer_norm_eps: epsilon of every layer norm (PyTorch's 1e-5).
        standardize: ``True``: each IMU channel enters the network as ``(x - mu) / sigma``
            (the training set's clean IMU statistics) and the network predicts in the units
            of the offset distribution, ``o_hat = m + s * head(...)`` (``m``, ``s``: its
            mean and standard deviation under the run's injection protocol), with the head
            zero-initialised so that an untrained model predicts the mean offset; the
            statistics travel with the checkpoint. ``False``: raw SI values in and out
            (accelerometer inputs near 9.81 m/s^2, paper-protocol targets of several
            m/s^2). The paper describes no normalisation; ``calib_ablation.py`` compares.
        frame_encoder_dtype: operand type of the frame encoder's matrix products (patch
            projection, its encoder's attention projections and feed-forward blocks: about
            90 % of a window's arithmetic). ``"float32"`` (default, the paper's and the
            PyTorch peer's numerics) or ``"bfloat16"``: operands rounded to bfloat16,
            products accumulated and returned in float32, everything else (attention
            weights, norms, the temporal/IMU/fusion blocks) float32. Integer pixels are
            exact in bfloat16, so the patch projection multiplies raw grayscale pixel values
            and scales the float32 product by ``pixel_scale``: its only rounding is the
            kernel's. Twice the matrix throughput on CPUs with bfloat16 dot products
            (AVX512-BF16, AMX) and on accelerators. The parameters stay float32, so a
            checkpoint loads under either value (``uavcal calib predict --frame-dtype``).
        closed_form: the closed-form estimate the head's output is added to (a learned
            correction, zero-initialised, so an untrained model predicts the closed form):
            ``"none"`` (the paper: the head alone; standardised, it starts at the mean
            offset) or ``"window_mean"`` (each window's mean IMU sample minus the training
            set's mean, the no-learning estimate that the paper protocol's offsets, drawn
            around the IMU's mean, make strong; needs ``standardize``, whose statistics it
            uses) or ``"rotation_ls"`` (gyro channels: the least-squares gyro error of the
            window's rotation residuals, ``-sum(dt_k^2 r_k) / sum(dt_k^2)`` over its valid
            intervals, the mean ``-r_k`` for equal intervals (see ``motion_tokens``); other
            channels, and a window without a valid interval: the mean offset; needs
            ``motion_tokens`` and ``standardize``) or ``"rotation_window_mean"`` (the gyro
            as ``rotation_ls``, the other channels as ``window_mean``: the paper protocol's
            strong no-learning estimate on the accelerometer, whose offsets are drawn around
            the IMU's mean, with the camera's on the gyro) or ``"rotation_alignment"`` (the
            gyro as ``rotation_ls``, the accelerometer from the window's visual-inertial
            alignment of the stereo VIO's metric poses, ``window.accel_start=alignment``:
            the metric start, whose standard deviation the model also reads; needs a
            6-channel model).
        motion_tokens: add one rotation-residual token per frame interval to the fused
            sequence (summed with ``T_v + T_i``, as eq. 10 sums those): ``r_k = Log(dR_gyro^T
            dR_cam) / dt`` (rad/s, body frame), ``dR_gyro`` the interval's full-rate gyro
            composed, ``dR_cam`` the body rotation seen by the camera (or the ground truth,
            ``window.rotations``); ``r_k ~ -(gyro bias + offset)``. Needs windows cut with
            ``window.rotations`` other than ``"none"``; the gyro is taken as the first three
            IMU channels (a 3-channel model must be a gyro model).
        correction_scale: the unit of the learned correction on the channels a closed form
            estimates (the gyro under ``rotation_ls``, every channel under
            ``window_mean`` and ``rotation_window_mean``), as a fraction of the offset's
            standard deviation: the head's output ``y`` adds ``correction_scale *
            offset_std * y`` there. The rotation residuals' least squares is already within
            about 1e-3 rad/s of the gyro error, so a correction in the offset's own units
            (1.0) lets training noise undo it; the shipped weights use 0.05. Channels
            without a closed form keep the full unit.
        variance: also predict each channel's uncertainty: a second head on the decoder's
            output (its gradient stopped there) gives a value per channel, ``v``, and the
            model returns ``(B, 2C)``: the offsets, then
            ``log sigma`` with ``sigma = correction unit * offset_std * exp(v)`` (``v``
            zero-initialised: an untrained model claims one correction unit), the standard
            deviation of the estimate's error (rad/s, m/s^2).
            :func:`~uavcal_jax.calib.model.split_prediction` splits them. It is trained by
            the Gaussian negative log-likelihood of the label (``LossConfig.w_nll``) with the
            offsets' gradient stopped, so the estimate learns as without it (the same
            parameters step for step, to rounding; early stopping's validation loss holds
            the NLL too, so the epoch kept may differ); needs ``standardize``.
        tilt_head: an auxiliary head for tilt (issue 20): a linear map of each frame's row
            of the fusion encoder's output (eq. 10) to ``up (3,)``, the direction of
            gravity's reaction in the IMU frame at that frame, trained against the ground
            truth's orientation (``LossConfig.w_tilt``). The accelerometer's window mean
            holds gravity's projection plus the offset; the head makes the shared features
            learn where gravity lies, so that the offset head can take it out. It is sown
            as the intermediate ``tilt`` ``(B, n, 3)``; the model's output and inference
            are unchanged. Training needs recordings with ground truth.
    """

    d_model: int = 256
    heads: int = 8
    layers: int = 2
    ff_dim: int | None = None
    activation: str = "relu"
    dropout: float = 0.01
    patch: tuple[int, int] = (64, 64)
    rgb: bool = False
    imu_channels: int = 6
    use_video: bool = True
    frame_token: str = "learned"
    max_frames: int | None = None
    norm_first: bool = False
    pixel_scale: float = 1.0 / 255.0
    layer_norm_eps: float = 1e-5
    standardize: bool = True
    frame_encoder_dtype: str = "float32"
    closed_form: str = "none"
    motion_tokens: bool = False
    correction_scale: float = 1.0
    variance: bool = False
    tilt_head: bool = False

    def __post_init__(self) -> None:
        if self.d_model <= 0 or self.heads <= 0 or self.d_model % self.heads:
            raise ValueError(f"d_model ({self.d_model}) must be a positive multiple of heads "
                             f"({self.heads})")
        if self.layers < 1:
            raise ValueError(f"layers must be >= 1, got {self.layers}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if len(self.patch) != 2 or min(self.patch) <= 0:
            raise ValueError(f"patch must be (height, width) > 0, got {self.patch}")
        if self.imu_channels not in (3, 6):
            raise ValueError(f"imu_channels must be 3 or 6, got {self.imu_channels}")
        if self.frame_token not in FRAME_TOKENS:
            raise ValueError(f"frame_token must be one of {FRAME_TOKENS}, "
                             f"got {self.frame_token!r}")
        if self.closed_form not in CLOSED_FORMS:
            raise ValueError(f"closed_form must be one of {CLOSED_FORMS}, "
                             f"got {self.closed_form!r}")
        if self.closed_form != "none" and not self.standardize:
            raise ValueError(f"closed_form={self.closed_form!r} needs standardize (the "
                             "training statistics it subtracts)")
        if self.closed_form == "rotation_alignment" and self.imu_channels != 6:
            raise ValueError("closed_form='rotation_alignment' starts the accelerometer: it "
                             "needs imu_channels=6")
        if self.closed_form in ROTATION_CLOSED_FORMS and not self.motion_tokens:
            raise ValueError(f"closed_form={self.closed_form!r} needs motion_tokens (the "
                             "rotation residuals it solves from)")
        if self.variance and not self.standardize:
            raise ValueError("variance needs standardize (its unit is the offsets' spread)")
        if not self.correction_scale > 0:
            raise ValueError(f"correction_scale must be > 0, got {self.correction_scale}")
        if self.frame_encoder_dtype not in FRAME_ENCODER_DTYPES:
            raise ValueError(f"frame_encoder_dtype must be one of {FRAME_ENCODER_DTYPES}, "
                             f"got {self.frame_encoder_dtype!r}")

    @property
    def ff_width(self) -> int:
        """The feed-forward hidden width actually used."""
        return 4 * self.d_model if self.ff_dim is None else self.ff_dim


@dataclass(frozen=True)
class LossConfig:
    """The loss of eq. 15-18: ``w_o * L_offset + w_s * L_sign + w_m * L_magnitude``.

    Attributes:
        sign_term: ``"sign"`` (as written: ``MSE(sign(o_hat), sign(o))``, zero gradient almost
            everywhere) or ``"tanh"`` (smooth surrogate ``MSE(tanh(o_hat / tau), sign(o))``).
        tau: temperature of the surrogate, in the offsets' units (rad/s, m/s^2).
        w_offset, w_sign, w_magnitude: term weights (the paper sums them: all 1).
        units: ``"si"``: the offset and magnitude MSEs in rad/s and m/s^2 mixed (as
            written); ``"standardized"``: each channel's differences in units of the
            protocol's offset standard deviation (see :mod:`uavcal_jax.calib.loss`).
        w_nll: weight of the Gaussian negative log-likelihood that trains a model's
            uncertainty (``ModelConfig.variance``; unused without it).
        w_tilt: weight of the tilt head's loss, the mean squared difference between the
            predicted and the true unit up vector over real frames
            (:func:`~uavcal_jax.calib.loss.tilt_loss`; ``ModelConfig.tilt_head``, unused
            without it).
    """

    sign_term: str = "sign"
    tau: float = 0.05
    w_offset: float = 1.0
    w_sign: float = 1.0
    w_magnitude: float = 1.0
    units: str = "si"
    w_nll: float = 1.0
    w_tilt: float = 1.0

    def __post_init__(self) -> None:
        if self.sign_term not in SIGN_TERMS:
            raise ValueError(f"sign_term must be one of {SIGN_TERMS}, got {self.sign_term!r}")
        if self.units not in LOSS_UNITS:
            raise ValueError(f"units must be one of {LOSS_UNITS}, got {self.units!r}")
        if self.tau <= 0:
            raise ValueError(f"tau must be positive, got {self.tau}")
        if self.w_nll < 0:
            raise ValueError(f"w_nll must be >= 0, got {self.w_nll}")
        if self.w_tilt < 0:
            raise ValueError(f"w_tilt must be >= 0, got {self.w_tilt}")


@dataclass(frozen=True)
class InjectionConfig:
    """How training/validation offsets are drawn (section 3.4, eq. 12): the injection protocol.

    Attributes:
        protocol: ``"paper"``: per channel ``o ~ N(mu, n_m * sigma^2)`` (variance ``n_m``
            times the training set's, so the standard deviation is ``sqrt(n_m) * sigma``);
            ``"symmetric"``: per channel ``o ~ U(-n_m * sigma, n_m * sigma)``, the interval
            variant of the text; ``"physical"``: per channel ``U(-r, r)`` with ``r`` =
            ``gyro_range`` (rad/s) or ``accel_range`` (m/s^2), independent of the data.
        noise_multiplier: ``n_m`` (2).
        gyro_range: physical protocol, per-axis bound of gyro offsets, rad/s. A per-axis
            ``U(-r, r)`` has an RMS norm of ``r``: 0.08 rad/s, the size of EuRoC's
            ground-truth gyro biases.
        accel_range: physical protocol, per-axis bound of accel offsets, m/s^2 (0.16: EuRoC's
            accelerometer biases in norm).
        single_sensor: physical protocol with a 3-channel IMU: which range applies
            (``"gyro"`` or ``"accel"``).
        label: what the model learns to predict (:data:`uavcal_jax.data.true_offset.LABELS`):
            ``"injected"``, the drawn offset alone (the paper's label), or ``"total"``, the
            offset plus the sensor's own bias over the window from the ground truth's bias
            columns (the constant a user subtracts). ``None``: the protocol's default,
            ``total`` under ``physical`` and ``injected`` otherwise (:attr:`target`).
    """

    protocol: str = "paper"
    noise_multiplier: float = 2.0
    gyro_range: float = EUROC_BIAS_SCALE[0]
    accel_range: float = EUROC_BIAS_SCALE[1]
    single_sensor: str = "gyro"
    label: str | None = None

    @property
    def target(self) -> str:
        """The label in force: :attr:`label`, or the protocol's default when it is ``None``."""
        if self.label is not None:
            return self.label
        return "total" if self.protocol == "physical" else "injected"

    def __post_init__(self) -> None:
        if self.single_sensor not in ("gyro", "accel"):
            raise ValueError(f"single_sensor must be 'gyro' or 'accel', "
                             f"got {self.single_sensor!r}")
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        if self.label is not None and self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS} or none, got {self.label!r}")
        if self.noise_multiplier <= 0 or self.gyro_range < 0 or self.accel_range < 0:
            raise ValueError("noise_multiplier must be positive and the ranges non-negative")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation (Table 2, section 4.4).

    Attributes:
        batch_size: windows per step (16; the paper uses 8 for its long Zurich-like sequence).
        learning_rate: AdamW learning rate (1e-5).
        weight_decay: AdamW decoupled weight decay (0.01, PyTorch's AdamW default, which the
            paper's PyTorch implementation inherits).
        b1, b2, eps: AdamW moments and epsilon (PyTorch's defaults).
        epochs: most epochs to run.
        patience: stop after this many epochs without improvement (3).
        seed: base seed.
        seeds: ``K`` independently initialised models trained in one vmapped step.
        freeze_key_bias: zero the attention key biases' gradients (exactly zero in exact
            arithmetic; see :func:`uavcal_jax.calib.train.make_optimizer`).
        mounting: ``"fixed"`` (the recordings' own IMU mounting) or ``"random"``: every
            training window's IMU turned by its own uniformly random rotation, the frames
            kept, and the IMU standardised with statistics that hold for any mounting
            (:mod:`uavcal_jax.calib.mounting`): a model that does not depend on how the IMU
            sits in the airframe. Not with the paper protocol (its offsets are drawn around
            the recorded mounting's mean).
    """

    batch_size: int = 16
    learning_rate: float = 1e-5
    weight_decay: float = 0.01
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    epochs: int = 100
    patience: int = 3
    seed: int = 0
    seeds: int = 1
    freeze_key_bias: bool = True
    mounting: str = "fixed"

    def __post_init__(self) -> None:
        if self.mounting not in MOUNTINGS:
            raise ValueError(f"mounting must be one of {MOUNTINGS}, got {self.mounting!r}")
        if self.batch_size < 1 or self.epochs < 1 or self.patience < 1 or self.seeds < 1:
            raise ValueError("batch_size, epochs, patience and seeds must be >= 1")
        if self.learning_rate <= 0 or self.weight_decay < 0:
            raise ValueError("learning_rate must be positive and weight_decay non-negative")


@dataclass(frozen=True)
class LoopConfig:
    """Run control around the steps (:mod:`uavcal_jax.calib.loop`).

    Attributes:
        monitor: early stopping and best-model criterion: ``"train"`` (section 4.4: the
            epoch's training loss) or ``"val"`` (validation loss).
        keep: last checkpoints kept (plus the best).
        validation: the validation scheme: ``"split"`` (fixed random split over windows),
            ``"loo"`` (leave one sequence out), ``"kfold"`` (contiguous blocks of windows).
        val_fraction: the split's validation share (0.2: the ablation's 80/20).
        split_seed: seed of the split.
        folds: ``k`` of k-fold.
        val_offsets: offsets per validation: the validation windows are evaluated once per
            offset, each shared by every window (the paper's one offset per trial), and the
            metrics pooled. 1 is the paper's single draw; its figures then hang on that
            draw's luck (a draw near the training mean flatters the mean-offset baseline).
    """

    monitor: str = "train"
    keep: int = 2
    validation: str = "split"
    val_fraction: float = 0.2
    split_seed: int = 0
    folds: int = 5
    val_offsets: int = 8

    def __post_init__(self) -> None:
        if self.monitor not in MONITORS:
            raise ValueError(f"monitor must be one of {MONITORS}, got {self.monitor!r}")
        if self.validation not in VALIDATIONS:
            raise ValueError(f"validation must be one of {VALIDATIONS}, "
                             f"got {self.validation!r}")
        if (self.keep < 1 or self.folds < 2 or self.val_offsets < 1
                or not 0.0 < self.val_fraction < 1.0):
            raise ValueError("keep, val_offsets must be >= 1, folds >= 2 and val_fraction in "
                             "(0, 1)")


@dataclass(frozen=True)
class CalibConfig:
    """The network and its training, one section per concern: what a
    :class:`~uavcal_jax.calib.train.CalibState` carries (static) and the jitted steps read."""

    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    injection: InjectionConfig = field(default_factory=InjectionConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        check_sections(self.injection, self.train, self.model)


def check_sections(injection: InjectionConfig, train: TrainConfig,
                   model: ModelConfig | None = None) -> None:
    """Refuse sections that do not combine: random mountings under the paper protocol or
    with the metric accelerometer start (solved in the recorded mounting)."""
    if train.mounting == "random" and injection.protocol == "paper":
        raise ValueError("train.mounting=random does not combine with injection.protocol="
                         "paper (its offsets are drawn around the recorded mounting's mean)")
    if (train.mounting == "random" and model is not None
            and model.closed_form == "rotation_alignment"):
        raise ValueError("train.mounting=random does not combine with model.closed_form="
                         "rotation_alignment (its start is solved in the recorded mounting)")


@dataclass(frozen=True)
class CalibRunConfig:
    """A calibrator run's whole configuration: the root of ``--set`` keys
    (``model.d_model=64``, ``loop.validation=loo``, ``window.size=160x96``) and of a run's
    ``config.json``. The first four sections are :class:`CalibConfig`'s (:attr:`calib`)."""

    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    injection: InjectionConfig = field(default_factory=InjectionConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    window: WindowConfig = field(default_factory=WindowConfig)

    def __post_init__(self) -> None:
        check_sections(self.injection, self.train, self.model)
        if (self.model.closed_form == "rotation_alignment"
                and self.window.accel_start != "alignment"):
            raise ValueError("model.closed_form=rotation_alignment needs windows with the "
                             "metric start: window.accel_start=alignment")

    @property
    def calib(self) -> CalibConfig:
        """The network-and-training sections."""
        return CalibConfig(**{f.name: getattr(self, f.name) for f in fields(CalibConfig)})

    @classmethod
    def of(cls, calib: CalibConfig, loop: LoopConfig | None = None,
           window: WindowConfig | None = None) -> CalibRunConfig:
        """The root of ``calib``'s sections, ``loop`` and ``window`` (``None``: defaults)."""
        return cls(**{f.name: getattr(calib, f.name) for f in fields(CalibConfig)},
                   loop=LoopConfig() if loop is None else loop,
                   window=WindowConfig() if window is None else window)


def run_layout(stored: Mapping) -> dict:
    """A stored run record (``config.json``, a checkpoint's ``meta["config"]``) in the root's
    layout: records written before :class:`CalibRunConfig` (the shipped weights among them)
    nest ``model``, ``loss``, ``injection`` and ``train`` under ``"calib"``; they are lifted to
    the top. :data:`RUN_EXTRAS` entries are kept."""
    nested = stored.get("calib", {})
    return {**nested, **{k: v for k, v in stored.items() if k != "calib"}}

