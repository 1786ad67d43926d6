"""Building blocks shared by the detectors (Flax linen, float32, NHWC).

* activations: :func:`hardswish` (RPEOD eq. 11, ``x * relu6(x + 3) / 6``), :func:`hardsigmoid`;
* :class:`ConvBNAct`: convolution without bias, batch norm, activation, torch-style symmetric
  padding ``k // 2`` (so stride-2 layers see the same pixels as the PyTorch originals);
* :class:`DepthwiseConv`: a depthwise convolution with Flax's grouped-conv parameter layout
  ``kernel (k, k, 1, C)``, computed either as a grouped ``conv_general_dilated`` or as a sum of
  ``k*k`` shifted, per-channel-scaled slices of the padded input (``impl="shift"``), which XLA's
  CPU backend fuses into a few elementwise loops and runs many times faster (see
  ``experiments/bench_detector.py --dw-sweep``);
* :class:`SqueezeExcite`, :class:`InvertedResidual` (MobileNetV3's bneck: expand 1x1,
  depthwise kxk, SE, linear 1x1 projection, residual where shapes allow);
* YOLOv5 v7.0 ``models/common.py`` blocks: :class:`Conv` (conv-BN-SiLU), :class:`Bottleneck`,
  :class:`C3`, :class:`SPPF`.

Weights are initialised like PyTorch's default for ``nn.Conv2d``/``nn.Linear`` (uniform with
bound ``1/sqrt(fan_in)``), which is what YOLOv5 trains from.
"""

from __future__ import annotations

from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.detect.config import BN_EPS, BN_MOMENTUM

F32 = jnp.float32

#: PyTorch's default conv/linear weight init (kaiming_uniform with a=sqrt(5)).
torch_default_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def torch_bias_init(fan_in: int):
    bound = 1.0 / max(fan_in, 1) ** 0.5

    def init(key, shape, dtype=F32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def hardsigmoid(x):
    return jax.nn.relu6(x + 3.0) / 6.0


def hardswish(x):
    """RPEOD eq. (11): ``h-swish(x) = x * ReLU6(x + 3) / 6``."""
    return x * jax.nn.relu6(x + 3.0) / 6.0


def identity(x):
    return x


ACTIVATIONS: dict[str, Callable] = {
    "relu": jax.nn.relu,
    "hswish": hardswish,
    "silu": jax.nn.silu,
    "none": identity,
}


def make_divisible(v: float, divisor: int = 8, min_value: int | None = None) -> int:
    """MobileNet's channel rounding: nearest multiple of ``divisor``, never below 90 % of v."""
    min_value = min_value or divisor
    new_v = max(min_value, int(v + divisor / 2) // divisor * divisor)
    if new_v < 0.9 * v:
        new_v += divisor
    return new_v


def _pad(k: int) -> tuple[tuple[int, int], tuple[int, int]]:
    p = k // 2
    return ((p, p), (p, p))


def conv_s2d(x, kernel, padding: int):
    """A stride-2 ``k x k`` convolution (symmetric ``padding``) of an even-sized NHWC input,
    computed as a stride-1 convolution of its 2x2 space-to-depth rearrangement.

    Tap ``d`` in ``[-p, k-1-p]`` of output ``i`` reads input row ``2i + d``, i.e. block row
    ``i + floor(d/2)`` at parity ``d mod 2``; the block kernel is assembled from ``kernel``.
    XLA:CPU convolves 12 channels much faster than 3 strided ones (the stem is the layer with
    the largest output). Identical to the direct convolution up to float rounding.
    """
    b, h, w, c = x.shape
    k, _, _, o = kernel.shape
    lo, hi = (-padding) // 2, (k - 1 - padding) // 2  # block offsets
    kb = hi - lo + 1
    y = x.reshape(b, h // 2, 2, w // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
    y = y.reshape(b, h // 2, w // 2, 4 * c)
    k4 = jnp.zeros((kb, kb, 2, 2, c, o), kernel.dtype)
    for di in range(-padding, k - padding):
        for dj in range(-padding, k - padding):
            bi, pi = di // 2 - lo, di % 2
            bj, pj = dj // 2 - lo, dj % 2
            k4 = k4.at[bi, bj, pi, pj].set(kernel[di + padding, dj + padding])
    k4 = k4.reshape(kb, kb, 4 * c, o)
    ho = (h + 2 * padding - k) // 2 + 1
    wo = (w + 2 * padding - k) // 2 + 1
    pad_h = (-lo, ho - 1 + hi - (h // 2 - 1))
    pad_w = (-lo, wo - 1 + hi - (w // 2 - 1))
    return jax.lax.conv_general_dilated(
        y, k4, (1, 1), (pad_h, pad_w), dimension_numbers=("NHWC", "HWIO", "NHWC")
    )


class Conv2D(nn.Module):
    """``nn.Conv`` with the same parameters (``kernel (k, k, C_in, C_out)``, optional ``bias``)
    and torch-style padding ``k // 2`` (or ``padding``), computed as a plain matrix product
    when the kernel is 1x1 (XLA:CPU runs ``dot`` about twice as fast as a 1x1 convolution) and
    via space-to-depth for stride-2 convolutions of 3-channel images (the stems; see
    :func:`conv_s2d`), otherwise as ``conv_general_dilated`` (NHWC/HWIO)."""

    features: int
    kernel_size: int = 1
    stride: int = 1
    padding: int | None = None
    use_bias: bool = False
    kernel_init: Callable = torch_default_init
    bias_init: Callable | None = None

    @nn.compact
    def __call__(self, x):
        k = self.kernel_size
        cin = x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (k, k, cin, self.features), F32)
        p = k // 2 if self.padding is None else self.padding
        if k == 1 and self.stride == 1 and p == 0:
            y = jnp.dot(x, kernel[0, 0], preferred_element_type=F32)
        elif self.stride == 2 and cin <= 4 and x.shape[1] % 2 == 0 and x.shape[2] % 2 == 0:
            y = conv_s2d(x, kernel, p)
        else:
            y = jax.lax.conv_general_dilated(
                x,
                kernel,
                window_strides=(self.stride, self.stride),
                padding=((p, p), (p, p)),
                dimension_numbers=("NHWC", "HWIO", "NHWC"),
            )
        if self.use_bias:
            bias_init = self.bias_init or torch_bias_init(k * k * cin)
            y = y + self.param("bias", bias_init, (self.features,), F32)
        return y


# --------------------------------------------------------------------------------------------
# depthwise convolution


def depthwise_shift(x, kernel, stride: int = 1):
    """Depthwise conv as a sum of shifted slices; ``kernel`` is (k, k, 1, C), padding k//2."""
    k = kernel.shape[0]
    p = k // 2
    b, h, w, c = x.shape
    ho = (h + 2 * p - k) // stride + 1
    wo = (w + 2 * p - k) // stride + 1
    xp = jnp.pad(x, ((0, 0), (p, p), (p, p), (0, 0)))
    out = None
    for i in range(k):
        for j in range(k):
            sl = jax.lax.slice(
                xp,
                (0, i, j, 0),
                (b, i + (ho - 1) * stride + 1, j + (wo - 1) * stride + 1, c),
                (1, stride, stride, 1),
            )
            term = sl * kernel[i, j, 0]
            out = term if out is None else out + term
    return out


def depthwise_grouped(x, kernel, stride: int = 1):
    """Depthwise conv as Flax does it: a grouped ``conv_general_dilated`` (NHWC/HWIO)."""
    k = kernel.shape[0]
    return jax.lax.conv_general_dilated(
        x,
        kernel,
        window_strides=(stride, stride),
        padding=_pad(k),
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        feature_group_count=x.shape[-1],
    )


class DepthwiseConv(nn.Module):
    """Depthwise kxk convolution, no bias; parameters identical to
    ``nn.Conv(C, (k, k), feature_group_count=C, use_bias=False)``."""

    kernel_size: int
    stride: int = 1
    impl: str = "shift"

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        k = self.kernel_size
        kernel = self.param("kernel", torch_default_init, (k, k, 1, c), F32)
        if self.impl == "grouped":
            return depthwise_grouped(x, kernel, self.stride)
        return depthwise_shift(x, kernel, self.stride)


# --------------------------------------------------------------------------------------------
# generic conv-bn-act


class ConvBNAct(nn.Module):
    """Conv (no bias) -> BatchNorm -> activation; a depthwise conv when ``depthwise``."""

    features: int
    kernel_size: int = 1
    stride: int = 1
    act: str = "relu"
    depthwise: bool = False
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS
    dw_impl: str = "shift"

    @nn.compact
    def __call__(self, x, train: bool = False):
        k = self.kernel_size
        if self.depthwise:
            x = DepthwiseConv(k, self.stride, self.dw_impl, name="conv")(x)
        else:
            x = Conv2D(self.features, k, self.stride, name="conv")(x)
        x = nn.BatchNorm(
            use_running_average=not train,
            momentum=self.bn_momentum,
            epsilon=self.bn_eps,
            dtype=F32,
            param_dtype=F32,
            name="bn",
        )(x)
        return ACTIVATIONS[self.act](x)


class Dense(nn.Module):
    """Linear layer with PyTorch's default init."""

    features: int

    @nn.compact
    def __call__(self, x):
        fan_in = x.shape[-1]
        return nn.Dense(
            self.features,
            dtype=F32,
            param_dtype=F32,
            kernel_init=torch_default_init,
            bias_init=torch_bias_init(fan_in),
        )(x)


# --------------------------------------------------------------------------------------------
# MobileNetV3-style blocks


class SqueezeExcite(nn.Module):
    """Channel attention (RPEOD 4.1): global average pool -> FC(squeeze) -> ReLU -> FC ->
    hard sigmoid -> rescale the channels."""

    squeeze: int

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        s = jnp.mean(x, axis=(1, 2), keepdims=True)
        s = jax.nn.relu(Dense(self.squeeze, name="fc1")(s))
        s = hardsigmoid(Dense(c, name="fc2")(s))
        return x * s


class InvertedResidual(nn.Module):
    """MobileNetV2/V3 inverted residual with linear bottleneck (RPEOD 4.4).

    1x1 expansion to ``hidden`` channels (skipped when ``hidden == in``), depthwise kxk with
    stride, optional SE (squeeze ``make_divisible(hidden/4)``), linear 1x1 projection with BN
    and no activation; identity shortcut when stride is 1 and channels are unchanged.
    """

    hidden: int
    out: int
    kernel_size: int = 3
    stride: int = 1
    use_se: bool = True
    act: str = "hswish"
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS
    dw_impl: str = "shift"

    @nn.compact
    def __call__(self, x, train: bool = False):
        cin = x.shape[-1]
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        y = x
        if self.hidden != cin:
            y = ConvBNAct(self.hidden, 1, 1, self.act, name="expand", **bn)(y, train)
        y = ConvBNAct(
            self.hidden,
            self.kernel_size,
            self.stride,
            self.act,
            depthwise=True,
            dw_impl=self.dw_impl,
            name="dw",
            **bn,
        )(y, train)
        if self.use_se:
            y = SqueezeExcite(make_divisible(self.hidden / 4, 8), name="se")(y)
        y = ConvBNAct(self.out, 1, 1, "none", name="project", **bn)(y, train)
        if self.stride == 1 and cin == self.out:
            y = y + x
        return y


# --------------------------------------------------------------------------------------------
# YOLOv5 v7.0 blocks (models/common.py)


class Conv(nn.Module):
    """YOLOv5 ``Conv``: conv (no bias, autopad k//2 unless given) -> BN -> SiLU."""

    features: int
    kernel_size: int = 1
    stride: int = 1
    padding: int | None = None
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, x, train: bool = False):
        k = self.kernel_size
        p = k // 2 if self.padding is None else self.padding
        x = Conv2D(self.features, k, self.stride, p, name="conv")(x)
        x = nn.BatchNorm(
            use_running_average=not train,
            momentum=self.bn_momentum,
            epsilon=self.bn_eps,
            dtype=F32,
            param_dtype=F32,
            name="bn",
        )(x)
        return jax.nn.silu(x)


class Bottleneck(nn.Module):
    """YOLOv5 ``Bottleneck(c1, c2, shortcut, e=1.0)``: 1x1 then 3x3, residual if c1 == c2."""

    features: int
    shortcut: bool = True
    expansion: float = 1.0
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        c_ = int(self.features * self.expansion)
        y = Conv(c_, 1, 1, name="cv1", **bn)(x, train)
        y = Conv(self.features, 3, 1, name="cv2", **bn)(y, train)
        return x + y if (self.shortcut and x.shape[-1] == self.features) else y


class C3(nn.Module):
    """YOLOv5 ``C3``: CSP bottleneck with three convolutions."""

    features: int
    n: int = 1
    shortcut: bool = True
    expansion: float = 0.5
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        c_ = int(self.features * self.expansion)
        a = Conv(c_, 1, 1, name="cv1", **bn)(x, train)
        for i in range(self.n):
            a = Bottleneck(c_, self.shortcut, 1.0, name=f"m_{i}", **bn)(a, train)
        b = Conv(c_, 1, 1, name="cv2", **bn)(x, train)
        return Conv(self.features, 1, 1, name="cv3", **bn)(jnp.concatenate([a, b], -1), train)


def max_pool_same(x, k: int):
    """Stride-1 max pool with padding k//2 (``nn.MaxPool2d(k, 1, k // 2)``), separably as the
    maximum of ``k`` shifted slices along each axis (XLA:CPU's ``reduce_window`` is several
    times slower on these small maps)."""
    p = k // 2
    b, h, w, c = x.shape
    xp = jnp.pad(x, ((0, 0), (p, p), (0, 0), (0, 0)), constant_values=-jnp.inf)
    y = xp[:, 0:h]
    for i in range(1, k):
        y = jnp.maximum(y, xp[:, i:i + h])
    yp = jnp.pad(y, ((0, 0), (0, 0), (p, p), (0, 0)), constant_values=-jnp.inf)
    z = yp[:, :, 0:w]
    for j in range(1, k):
        z = jnp.maximum(z, yp[:, :, j:j + w])
    return z


class SPPF(nn.Module):
    """YOLOv5 ``SPPF(c1, c2, k=5)``: three chained 5x5 max pools, concatenated."""

    features: int
    k: int = 5
    bn_momentum: float = BN_MOMENTUM
    bn_eps: float = BN_EPS

    @nn.compact
    def __call__(self, x, train: bool = False):
        bn = dict(bn_momentum=self.bn_momentum, bn_eps=self.bn_eps)
        c_ = x.shape[-1] // 2
        x = Conv(c_, 1, 1, name="cv1", **bn)(x, train)
        y1 = max_pool_same(x, self.k)
        y2 = max_pool_same(y1, self.k)
        y3 = max_pool_same(y2, self.k)
        return Conv(self.features, 1, 1, name="cv2", **bn)(
            jnp.concatenate([x, y1, y2, y3], -1), train
        )


def upsample2(x):
    """Nearest-neighbour 2x upsampling (``nn.Upsample(None, 2, 'nearest')``)."""
    return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)
