"""The IMU-offset transformer of Avola et al. (Sensors 2023, 23, 2655), section 3, in Flax.

Shapes: ``B`` windows, ``n`` frames (and IMU samples, one per frame) per window, ``h x w``
frames, ``p`` patches per frame, ``d`` token width, ``C`` IMU channels (6: gyro xyz in
rad/s, accel xyz in m/s^2, the IMU/body frame).

- **Video reducer block (VRB).** Frames ``(B, n, h, w)`` grayscale or ``(B, n, 3, h, w)`` RGB,
  uint8 or float, scaled by ``pixel_scale``. RGB goes through the colour-compression CNN
  (a 3D convolution with kernel (1, 3, 3), i.e. a per-frame 3x3 convolution, an activation
  and batch norm, to one channel) and is summed with its grayscale image (eq. 1-2). Frames
  are zero-padded at the bottom/right to a multiple of the patch, unfolded into ``p``
  row-major patches, projected by ``Linear -> activation -> dropout`` (eq. 3), summed with
  learned positional embeddings, and one transformer encoder *shared by every frame* reads
  each frame's tokens; the output row of a learned first token is the frame's token (eq. 6).
  These frame tokens ``(B, n, d)`` plus learned temporal embeddings go through a temporal
  encoder (eq. 7): ``T_v``. ``ModelConfig.frame_encoder_dtype`` sets the operand type of
  this per-frame part's matrix products (float32, or bfloat16 with float32 sums).
- **IMU reducer block (IRB).** Each IMU vector ``(C,)`` through ``Linear -> activation ->
  dropout -> dropout -> Linear`` (eq. 8), plus learned positional embeddings, an encoder
  (eq. 9): ``T_i``.
- **Noise predictor block (NPB).** ``T_v + T_i`` plus positional embeddings through an
  encoder (eq. 10); a decoder whose target is one learned query ``L`` and whose memory is
  that encoder's output; a linear layer to the ``C`` offsets (eq. 11).

The IMU-only variant (``use_video=False``) drops the VRB: the NPB reads ``T_i`` alone.

With ``ModelConfig.standardize`` the IMU enters as ``(imu - imu_mean) / imu_std`` and the
head's output ``y`` becomes ``base + offset_std * y``; the four ``(C,)`` constants are
the ``"normalization"`` variable collection (:data:`NORMALIZATION`), which the caller supplies
from the training statistics (:meth:`uavcal_jax.calib.train.CalibState.variables`), and the
head starts at zero: an untrained model predicts ``base``, the closed-form estimate of
``ModelConfig.closed_form``: the mean offset ``offset_mean`` (the paper's head), or the
window's mean IMU sample minus ``imu_mean``, so that training learns a correction to it.

**Motion tokens** (``ModelConfig.motion_tokens``, issue 20): the frame tokens each see one
frame, but a gyro error shows only in how the camera's rotation over a frame interval differs
from the integrated gyro. For each interval ``k`` (``motion`` inputs:
:meth:`uavcal_jax.data.windows.WindowSet.motion`) :func:`rotation_residuals` gives
``r_k = Log(dR_gyro,k^T dR_cam,k) / dt_k`` (rad/s, body frame; ``dR_gyro`` the interval's
gyro samples composed, ``exp(w_1 dt_1) exp(w_2 dt_2) ...``), which is ``-(gyro error)`` for a
constant error and exact rotations. ``Dense((-r_k - m) / s)`` (``m``, ``s``: the gyro
channels' offset mean and standard deviation when standardised), zero on invalid intervals,
is summed into the fused sequence with ``T_v + T_i``. ``closed_form="rotation_ls"`` starts
the head at the rotation residuals' least-squares gyro error (``"rotation_window_mean"``: the
same, with the window mean on the accelerometer).

**Tilt** (``ModelConfig.tilt_head``): a linear head on each frame's row of the fusion
encoder's output predicts ``up (3,)``, gravity's reaction in the IMU frame at that frame,
sown as ``("intermediates", "tilt")`` ``(B, n, 3)`` (apply with ``mutable=["intermediates"]``
to read it; the returned offsets do not change).

**Uncertainty** (``ModelConfig.variance``): a second linear head on the decoder's output,
its gradient stopped there (the offsets' features are not trained by it), gives each channel's
log standard deviation of the estimate's error, ``log(unit) + v`` (``unit`` the correction's,
in rad/s or m/s^2), trained by the Gaussian negative log-likelihood
(:func:`uavcal_jax.calib.loss.gaussian_nll`).

The frame encoder depends on one frame only, so :meth:`Calibrator.encode_frames` and
:meth:`Calibrator.predict_from_frame_tokens` split the model at the frame tokens: over a
sequence each frame is encoded once and its token reused by every window holding it
(:mod:`uavcal_jax.calib.inference`).

Padded frames (``mask`` False) are never attended to by any token sequence after the frame
encoder, so they change nothing. The RGB batch norm keeps running statistics in the
``batch_stats`` collection (apply with ``mutable=["batch_stats"]`` when training); padded
frames are excluded from its batch statistics.

One module over 450 lines, one job: the network, its blocks and the closed forms its head
starts from; the layers it shares with nothing else are here, the generic ones in
:mod:`uavcal_jax.calib.layers`.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.calib.config import ROTATION_CLOSED_FORMS, ModelConfig
from uavcal_jax.calib.dropout import Dropout
from uavcal_jax.calib.layers import ACTIVATION_FNS, LINEAR_INIT, Decoder, Encoder, dot_general_for
from uavcal_jax.data.color import LUMA_WEIGHTS
from uavcal_jax.geometry import so3

__all__ = ["ALIGNMENT_INPUTS", "GRAY_WEIGHTS", "MOTION_KEYS", "NORMALIZATION",
           "NORMALIZATION_NAMES", "Calibrator", "compose_intervals", "patchify",
           "rotation_residuals", "split_prediction", "without_correction"]

F32 = jnp.float32

# The grayscale image of eq. 1, that the colour-compression output is added to, is the
# BT.601 luma of the frame, as the readers' and the renderer's gray frames are.
GRAY_WEIGHTS = LUMA_WEIGHTS

_embedding_init = nn.initializers.normal(stddev=0.02)

#: The variable collection of the standardisation constants, and their names (each ``(C,)``).
NORMALIZATION = "normalization"
NORMALIZATION_NAMES = ("imu_mean", "imu_std", "offset_mean", "offset_std")

#: The batch entries of the motion inputs (:meth:`uavcal_jax.data.windows.WindowSet.motion`).
MOTION_KEYS = ("gyro_seq", "dt_seq", "rot_cam", "rot_mask")
#: Those of the metric accelerometer start (``closed_form="rotation_alignment"``; the same
#: names as :data:`uavcal_jax.data.windows.ALIGNMENT_KEYS`): ``accel_start (B, 3)`` and its
#: ``accel_start_std (B, 3)``, m/s^2 (``accel_response`` stays with the batch: the trainer
#: moves the start with an injected offset).
ALIGNMENT_INPUTS = ("accel_start", "accel_start_std")


def compose_intervals(gyro_seq: jax.Array, dt_seq: jax.Array) -> jax.Array:
    """``(..., 3, 3)`` the body rotation over each interval from its gyro samples
    ``gyro_seq (..., S, 3)`` rad/s held for ``dt_seq (..., S)`` seconds (zero-order hold):
    ``exp(w_1 dt_1) exp(w_2 dt_2) ... exp(w_S dt_S)`` (body frame at the interval's start
    from its end; zero-duration padding is the identity)."""
    steps = so3.exp(jnp.asarray(gyro_seq, F32) * jnp.asarray(dt_seq, F32)[..., None])
    steps = jnp.moveaxis(steps, -3, 0)  # (S, ..., 3, 3)

    def mul(acc, step):
        return acc @ step, None

    out, _ = jax.lax.scan(mul, steps[0], steps[1:])
    return out


def rotation_residuals(gyro_seq, dt_seq, rot_cam, rot_mask) -> tuple[jax.Array, jax.Array]:
    """Rotation residuals ``r (..., 3)`` rad/s, body frame, and interval durations
    ``dt (...)`` seconds (0 where ``rot_mask`` is False) of the motion inputs (shapes as
    :meth:`uavcal_jax.data.windows.WindowSet.motion`): ``r_k = Log(dR_gyro^T rot_cam) / dt``
    with ``dR_gyro`` = :func:`compose_intervals`; zero on invalid intervals. For gyro
    samples ``w + e`` with a constant error ``e`` and exact ``rot_cam``, ``r = -e`` to first
    order in ``e dt``."""
    valid = jnp.asarray(rot_mask, bool)
    dt = jnp.where(valid, jnp.sum(jnp.asarray(dt_seq, F32), axis=-1), 0.0)
    d_gyro = compose_intervals(gyro_seq, dt_seq)
    eye = jnp.eye(3, dtype=F32)
    err = jnp.where(valid[..., None, None], jnp.swapaxes(d_gyro, -1, -2)
                    @ jnp.asarray(rot_cam, F32), eye)
    r = so3.log(err) / jnp.maximum(dt, 1e-9)[..., None]
    return jnp.where(valid[..., None], r, 0.0), dt


def patchify(frames: jax.Array, patch: tuple[int, int]) -> jax.Array:
    """Zero-pad ``frames (N, h, w)`` at the bottom/right to multiples of ``patch`` and unfold
    into non-overlapping row-major patches ``(N, p, ph * pw)``, each patch row-major."""
    ph, pw = patch
    n, h, w = frames.shape
    frames = jnp.pad(frames, ((0, 0), (0, -h % ph), (0, -w % pw)))
    gh, gw = frames.shape[1] // ph, frames.shape[2] // pw
    x = frames.reshape(n, gh, ph, gw, pw).transpose(0, 1, 3, 2, 4)
    return x.reshape(n, gh * gw, ph * pw)


def _positions(module: nn.Module, name: str, length: int, needed: int, d: int) -> jax.Array:
    """Learned embeddings ``(needed, d)``: the first rows of a ``(length, d)`` table."""
    table = module.param(name, _embedding_init, (length, d), F32)
    if needed > table.shape[0]:
        raise ValueError(f"{name}: {needed} positions needed, the model was built for "
                         f"{table.shape[0]} (ModelConfig.max_frames or the init batch)")
    return table[:needed]


class ColorCompression(nn.Module):
    """Eq. 1-2: RGB frames ``(N, 3, h, w)`` -> gray + BN(act(conv(RGB))), ``(N, h, w)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, rgb: jax.Array, valid: jax.Array | None, train: bool) -> jax.Array:
        gray = jnp.tensordot(jnp.asarray(GRAY_WEIGHTS, F32), rgb, axes=([0], [1]))
        x = jnp.moveaxis(rgb, 1, -1)  # (N, h, w, 3): flax convolves channel-last
        x = nn.Conv(1, (3, 3), padding="SAME", dtype=F32, param_dtype=F32,
                    kernel_init=LINEAR_INIT, name="conv")(x)
        x = ACTIVATION_FNS[self.config.activation](x)
        mask = None if valid is None else valid.reshape(-1, 1, 1, 1).astype(bool)
        # PyTorch's BatchNorm momentum 0.1 is flax's 0.9 (weight of the old running value).
        x = nn.BatchNorm(use_running_average=not train, momentum=0.9, epsilon=1e-5, dtype=F32,
                         param_dtype=F32, name="norm")(x, mask=mask)
        return gray + x[..., 0]


class FrameEncoder(nn.Module):
    """VRB, per-frame part (eq. 1-6): frames ``(N, h, w)`` / ``(N, 3, h, w)`` -> ``(N, d)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, frames, valid=None, *, deterministic: bool = True):
        c = self.config
        dtype = jnp.dtype(c.frame_encoder_dtype)
        x = jnp.asarray(frames)
        # Grayscale pixels enter a bfloat16 product unscaled (integers are exact there) and
        # the float32 product is scaled instead: the same map, one rounding fewer.
        scale_product = not c.rgb and dtype != F32
        if not scale_product:
            x = x.astype(F32) * F32(c.pixel_scale)
        if c.rgb:
            x = ColorCompression(c, name="ccn")(x, valid, not deterministic)
        tokens = patchify(x, c.patch).astype(dtype)  # (N, p, ph*pw)
        tokens = nn.Dense(c.d_model, dtype=dtype, param_dtype=F32, kernel_init=LINEAR_INIT,
                          dot_general=dot_general_for(
                              dtype, c.pixel_scale if scale_product else None),
                          name="patch_proj")(tokens)
        tokens = ACTIVATION_FNS[c.activation](tokens)
        tokens = Dropout(c.dropout)(tokens, deterministic=deterministic)
        n_tok = tokens.shape[1]
        if c.frame_token == "learned":
            first = self.param("frame_token", _embedding_init, (1, 1, c.d_model), F32)
            tokens = jnp.concatenate([jnp.broadcast_to(first, (tokens.shape[0], 1, c.d_model)),
                                      tokens], axis=1)
            n_tok += 1
        pos = self.param("pos_patch", _embedding_init, (n_tok, c.d_model), F32)
        if pos.shape[0] != n_tok:
            raise ValueError(f"frames give {tokens.shape[1]} tokens per frame, the model was "
                             f"built for {pos.shape[0]} (another frame or patch size)")
        out = Encoder(c, dtype, name="spatial_encoder")(
            tokens + pos, deterministic=deterministic, outputs=1)  # only row 0 is read
        return out[:, 0]


class VideoTemporal(nn.Module):
    """VRB, temporal part (eq. 7): frame tokens ``(B, n, d)`` -> ``T_v (B, n, d)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, frame_tokens, mask, *, deterministic: bool = True):
        c = self.config
        n = frame_tokens.shape[1]
        x = frame_tokens.astype(F32) + _positions(self, "pos_time", c.max_frames or n, n,
                                                  c.d_model)
        return Encoder(c, name="temporal_encoder")(x, mask, deterministic=deterministic)


class ImuReducer(nn.Module):
    """IRB (eq. 8-9): IMU ``(B, n, C)`` -> ``T_i (B, n, d)``."""

    config: ModelConfig

    @nn.compact
    def __call__(self, imu, mask, *, deterministic: bool = True):
        c = self.config
        n = imu.shape[1]
        x = nn.Dense(c.d_model, dtype=F32, param_dtype=F32, kernel_init=LINEAR_INIT,
                     name="linear1")(imu.astype(F32))
        x = ACTIVATION_FNS[c.activation](x)
        x = Dropout(c.dropout)(x, deterministic=deterministic)
        x = Dropout(c.dropout)(x, deterministic=deterministic)  # eq. 8 has two
        x = nn.Dense(c.d_model, dtype=F32, param_dtype=F32, kernel_init=LINEAR_INIT,
                     name="linear2")(x)
        x = x + _positions(self, "pos_imu", c.max_frames or n, n, c.d_model)
        return Encoder(c, name="imu_encoder")(x, mask, deterministic=deterministic)


class MotionTokens(nn.Module):
    """Rotation-residual tokens: ``z (B, n, 3)`` (standardised ``-r``) -> ``(B, n, d)``,
    zero where ``valid (B, n)`` is False."""

    config: ModelConfig

    @nn.compact
    def __call__(self, z, valid):
        x = nn.Dense(self.config.d_model, dtype=F32, param_dtype=F32, kernel_init=LINEAR_INIT,
                     name="linear")(z.astype(F32))
        return x * valid[..., None].astype(F32)


class AlignmentToken(nn.Module):
    """The metric start as one token summed into every fused slot: ``Dense`` of the start and
    the log of its standard deviation, both in offset units (``(B, 6)`` -> ``(B, 1, d)``), so
    the head knows how far the window's alignment can be trusted."""

    config: ModelConfig

    @nn.compact
    def __call__(self, z):
        x = nn.Dense(self.config.d_model, dtype=F32, param_dtype=F32, kernel_init=LINEAR_INIT,
                     name="linear")(z.astype(F32))
        return x[:, None, :]


class NoisePredictor(nn.Module):
    """NPB (eq. 10-11): ``T_v + T_i (B, n, d)`` -> offsets ``(B, C)`` (with ``variance``
    ``(B, 2C)``: then the uncertainty head's output)."""

    config: ModelConfig

    @nn.compact
    def __call__(self, tokens, mask, *, deterministic: bool = True):
        c = self.config
        n = tokens.shape[1]
        x = tokens + _positions(self, "pos_fusion", c.max_frames or n, n, c.d_model)
        memory = Encoder(c, name="encoder")(x, mask, deterministic=deterministic)
        if c.tilt_head:
            self.sow("intermediates", "tilt", nn.Dense(
                3, dtype=F32, param_dtype=F32, kernel_init=LINEAR_INIT, name="tilt_head")(memory))
        query = self.param("query", _embedding_init, (1, 1, c.d_model), F32)
        query = jnp.broadcast_to(query, (tokens.shape[0], 1, c.d_model))
        out = Decoder(c, name="decoder")(query, memory, mask, deterministic=deterministic)
        # standardised: start at the mean offset, so training only has to improve on it
        head_init = nn.initializers.zeros if c.standardize else LINEAR_INIT
        offsets = nn.Dense(c.imu_channels, dtype=F32, param_dtype=F32, kernel_init=head_init,
                           name="head")(out[:, 0])
        if not c.variance:
            return offsets
        # the uncertainty reads the offsets' features without training them: the estimate
        # learns exactly as without it
        scale = nn.Dense(c.imu_channels, dtype=F32, param_dtype=F32,
                         kernel_init=nn.initializers.zeros,
                         name="sigma_head")(jax.lax.stop_gradient(out[:, 0]))
        return jnp.concatenate([offsets, scale], axis=-1)


class Calibrator(nn.Module):
    """The whole model; see the module docstring.

    ``__call__(frames, imu, mask, motion=None, deterministic=True) -> offsets (B, C)``
    (``(B, 2C)`` with ``variance``: :func:`split_prediction`) with
    ``frames`` ``(B, n, h, w)`` / ``(B, n, 3, h, w)`` (ignored, may be ``None``, when
    ``use_video`` is False), ``imu (B, n, C)``, ``mask (B, n)`` bool (``True`` on real
    frames) and, with ``motion_tokens``, ``motion`` (:data:`MOTION_KEYS`).
    Dropout draws from the ``"dropout"`` rng stream when ``deterministic`` is False.
    """

    config: ModelConfig

    def setup(self) -> None:
        c = self.config
        if c.use_video:
            self.frame_encoder = FrameEncoder(c)
            self.video_temporal = VideoTemporal(c)
        self.imu_reducer = ImuReducer(c)
        if c.motion_tokens:
            self.motion_tokens = MotionTokens(c)
        if c.closed_form == "rotation_alignment":
            self.alignment_token = AlignmentToken(c)
        self.noise_predictor = NoisePredictor(c)
        if c.standardize:
            fills = (jnp.zeros, jnp.ones, jnp.zeros, jnp.ones)
            self.normalization = {name: self.variable(NORMALIZATION, name, fill,
                                                      (c.imu_channels,), F32)
                                  for name, fill in zip(NORMALIZATION_NAMES, fills, strict=True)}

    def encode_frames(self, frames, valid=None, *, deterministic: bool = True) -> jax.Array:
        """Frame tokens ``(..., d)`` of frames ``(..., h, w)`` (gray) or ``(..., 3, h, w)``
        (RGB), any leading shape; ``valid`` (leading shape) drops padded frames from the
        RGB batch norm's statistics. Each output row depends on its frame only (in
        deterministic mode)."""
        if not self.config.use_video:
            raise ValueError("the IMU-only model (use_video=False) has no frame encoder")
        frames = jnp.asarray(frames)
        lead = frames.shape[:-3] if self.config.rgb else frames.shape[:-2]
        flat = frames.reshape((-1,) + frames.shape[len(lead):])
        flat_valid = None if valid is None else jnp.asarray(valid).reshape(-1)
        tokens = self.frame_encoder(flat, flat_valid, deterministic=deterministic)
        return tokens.reshape(lead + (tokens.shape[-1],))

    def predict_from_frame_tokens(self, frame_tokens, imu, mask, motion=None, *,
                                  deterministic: bool = True) -> jax.Array:
        """Offsets ``(B, C)`` from frame tokens ``(B, n, d)`` (``None`` for the IMU-only
        model), IMU ``(B, n, C)``, ``mask (B, n)`` and, with ``motion_tokens``, ``motion``:
        a mapping holding :data:`MOTION_KEYS` (the gyro in ``gyro_seq`` carrying the same
        error as ``imu``)."""
        c = self.config
        mask = jnp.asarray(mask, bool)
        imu = jnp.asarray(imu, F32)
        raw = imu
        norm = None
        if c.standardize:
            norm = {k: v.value for k, v in self.normalization.items()}
            imu = (imu - norm["imu_mean"]) / norm["imu_std"]
        tokens = self.imu_reducer(imu, mask, deterministic=deterministic)
        if c.use_video:
            if frame_tokens is None:
                raise ValueError("the video model needs frame tokens")
            tokens = tokens + self.video_temporal(frame_tokens, mask,
                                                  deterministic=deterministic)
        residual = None
        if c.motion_tokens:
            if motion is None or any(k not in motion for k in MOTION_KEYS):
                raise ValueError(f"model.motion_tokens needs the motion inputs {MOTION_KEYS} "
                                 "(windows cut with window.rotations oracle or visual)")
            r, dt = rotation_residuals(*(motion[k] for k in MOTION_KEYS))
            valid = jnp.asarray(motion["rot_mask"], bool) & mask
            residual = (r, jnp.where(valid, dt, 0.0))
            m, s = (jnp.zeros(3, F32), jnp.ones(3, F32)) if norm is None else (
                norm["offset_mean"][:3], norm["offset_std"][:3])
            tokens = tokens + self.motion_tokens((-r - m) / s, valid)
        start = None
        if c.closed_form == "rotation_alignment":
            if any(k not in motion for k in ALIGNMENT_INPUTS):
                raise ValueError(f"closed_form='rotation_alignment' needs {ALIGNMENT_INPUTS} "
                                 "(windows cut with window.accel_start=alignment)")
            start = jnp.asarray(motion["accel_start"], F32)
            unit = norm["offset_std"][3:]
            tokens = tokens + self.alignment_token(jnp.concatenate(
                [(start - norm["offset_mean"][3:]) / unit,
                 jnp.log(jnp.asarray(motion["accel_start_std"], F32) / unit)], axis=-1))
        out = self.noise_predictor(tokens, mask, deterministic=deterministic)
        if c.standardize:
            channels = c.imu_channels
            unit = norm["offset_std"] * self._correction_unit(channels)
            offsets = (self._closed_form(raw, mask, norm, residual, start)
                       + unit * out[..., :channels])
            if not c.variance:
                return offsets
            return jnp.concatenate([offsets, jnp.log(unit) + out[..., channels:]], axis=-1)
        return out

    def _correction_unit(self, channels: int) -> jax.Array:
        """``(C,)`` the head's unit per channel, in offset standard deviations:
        ``correction_scale`` on the channels the closed form estimates, 1 elsewhere."""
        c = self.config
        covered = {"none": 0, "window_mean": channels, "rotation_ls": 3,
                   "rotation_window_mean": channels, "rotation_alignment": channels}[c.closed_form]
        return jnp.where(jnp.arange(channels) < covered, c.correction_scale, 1.0).astype(F32)

    def _closed_form(self, imu, mask, norm, residual=None, accel_start=None) -> jax.Array:
        """``(B, C)`` the estimate the standardised head corrects (``closed_form``): the
        mean offset, each window's mean sample (real slots) minus the training mean, or
        (``rotation_ls``, ``rotation_window_mean``) the gyro error that best explains the
        rotation residuals, ``argmin_e sum_k |dt_k r_k + dt_k e|^2 = -sum(dt_k^2 r_k) /
        sum(dt_k^2)``, with the mean offset (``rotation_ls``), the window mean
        (``rotation_window_mean``) or the window's metric ``accel_start`` (``(B, 3)``,
        ``rotation_alignment``) on the other channels, and the mean offset on the gyro of a
        window without a valid interval."""
        form = self.config.closed_form
        if form in ROTATION_CLOSED_FORMS:
            base = jnp.broadcast_to(norm["offset_mean"], imu.shape[:-2] + imu.shape[-1:])
            if form == "rotation_window_mean":
                base = _window_mean(imu, mask) - norm["imu_mean"]
            elif form == "rotation_alignment":
                base = jnp.concatenate([base[..., :3], accel_start], axis=-1)
            r, dt = residual
            w = jnp.square(dt)[..., None]
            total = jnp.sum(w, axis=-2)
            gyro = -jnp.sum(w * r, axis=-2) / jnp.maximum(total, 1e-12)
            gyro = jnp.where(total > 0, gyro, base[..., :3])
            return jnp.concatenate([gyro, base[..., 3:]], axis=-1)
        if form == "window_mean":
            return _window_mean(imu, mask) - norm["imu_mean"]
        return jnp.broadcast_to(norm["offset_mean"], imu.shape[:-2] + imu.shape[-1:])

    def __call__(self, frames, imu, mask, motion=None, *,
                 deterministic: bool = True) -> jax.Array:
        frame_tokens = None
        if self.config.use_video:
            frame_tokens = self.encode_frames(frames, mask, deterministic=deterministic)
        return self.predict_from_frame_tokens(frame_tokens, imu, mask, motion,
                                              deterministic=deterministic)


def split_prediction(out: jax.Array, config: ModelConfig
                     ) -> tuple[jax.Array, jax.Array | None]:
    """``(offsets (..., C), log_sigma (..., C) or None)`` of a model's output ``out``: with
    ``config.variance`` the output holds both (``(..., 2C)``), otherwise the offsets alone."""
    if not config.variance:
        return out, None
    c = config.imu_channels
    return out[..., :c], out[..., c:]


def without_correction(params: dict) -> dict:
    """``params`` with the offset head's weights and bias at zero (any leading seed axis):
    a standardised model then predicts its closed form alone (``ModelConfig.closed_form``),
    the learned part switched off on the same windows (the credit-assignment rows)."""
    npb = dict(params["noise_predictor"])
    npb["head"] = jax.tree.map(jnp.zeros_like, npb["head"])
    return {**params, "noise_predictor": npb}


def _window_mean(imu: jax.Array, mask: jax.Array) -> jax.Array:
    """``(B, C)`` each window's mean IMU sample over its real slots."""
    w = mask.astype(F32)[..., None]
    return jnp.sum(imu * w, axis=-2) / jnp.maximum(jnp.sum(w, axis=-2), 1.0)
