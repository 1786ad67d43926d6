"""Configuration of the IMU-offset transformer (Avola et al., Sensors 2023, 23, 2655).

Frozen dataclasses; every default is the paper's (section 3, Table 2) unless its docstring
says otherwise. The window geometry (10 s windows, 1 s stride, 320x180 frames, gray or RGB
decoding) is *not* repeated here: it lives in :class:`uavcal_jax.data.windows.WindowConfig`,
and the model reads frame size and frames per window from the arrays it is given.

Overrides, JSON and presets: :mod:`uavcal_jax.config` and :mod:`uavcal_jax.calib.protocols`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "ACTIVATIONS",
    "FRAME_ENCODER_DTYPES",
    "FRAME_TOKENS",
    "PROTOCOLS",
    "LOSS_UNITS",
    "SIGN_TERMS",
    "CalibConfig",
    "InjectionConfig",
    "LossConfig",
    "ModelConfig",
    "TrainConfig",
]

ACTIVATIONS = ("relu", "gelu")
FRAME_TOKENS = ("learned", "first_patch")
FRAME_ENCODER_DTYPES = ("float32", "bfloat16")
SIGN_TERMS = ("sign", "tanh")
LOSS_UNITS = ("si", "standardized")
PROTOCOLS = ("paper", "symmetric", "physical")


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
    """

    sign_term: str = "sign"
    tau: float = 0.05
    w_offset: float = 1.0
    w_sign: float = 1.0
    w_magnitude: float = 1.0
    units: str = "si"

    def __post_init__(self) -> None:
        if self.sign_term not in SIGN_TERMS:
            raise ValueError(f"sign_term must be one of {SIGN_TERMS}, got {self.sign_term!r}")
        if self.units not in LOSS_UNITS:
            raise ValueError(f"units must be one of {LOSS_UNITS}, got {self.units!r}")
        if self.tau <= 0:
            raise ValueError(f"tau must be positive, got {self.tau}")


@dataclass(frozen=True)
class InjectionConfig:
    """How training/validation offsets are drawn (section 3.4, eq. 12).

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
    """

    protocol: str = "paper"
    noise_multiplier: float = 2.0
    gyro_range: float = 0.08
    accel_range: float = 0.16
    single_sensor: str = "gyro"

    def __post_init__(self) -> None:
        if self.single_sensor not in ("gyro", "accel"):
            raise ValueError(f"single_sensor must be 'gyro' or 'accel', "
                             f"got {self.single_sensor!r}")
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
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

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.epochs < 1 or self.patience < 1 or self.seeds < 1:
            raise ValueError("batch_size, epochs, patience and seeds must be >= 1")
        if self.learning_rate <= 0 or self.weight_decay < 0:
            raise ValueError("learning_rate must be positive and weight_decay non-negative")


@dataclass(frozen=True)
class CalibConfig:
    """The whole calibrator configuration: one section per concern."""

    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    injection: InjectionConfig = field(default_factory=InjectionConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

