"""Parameter and multiply-add counts, taken from the layer shapes of a traced model.

:func:`count_params` sums the sizes of the ``params`` collection (BN scale and bias included,
running statistics not -- the convention of PyTorch's ``numel`` over ``parameters()``).
:func:`count_macs` traces ``module.apply`` with :func:`jax.eval_shape` (no arithmetic runs)
and intercepts every convolution and dense layer: a convolution producing ``(H_o, W_o, C_o)``
with a ``k x k`` kernel over ``C_i / groups`` input channels costs ``H_o W_o C_o k^2 C_i /
groups`` multiply-adds; a dense layer ``C_i x C_o`` per position. Batch norm, activations,
pooling, SE rescaling and residual additions are not counted (as in the MobileNet papers'
"MAdds"). FLOPs are reported as ``2 x MACs`` where a caller wants GFLOPs (YOLOv5's summary
uses that convention).
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from uavcal_jax.detect.layers import Conv2D, DepthwiseConv


def count_params(variables_or_params) -> int:
    tree = variables_or_params
    if isinstance(tree, dict) and "params" in tree:
        tree = tree["params"]
    return int(sum(math.prod(x.shape) for x in jax.tree.leaves(tree)))


def count_macs(module: nn.Module, input_shape, **apply_kwargs) -> int:
    """Multiply-adds of one forward pass of ``module`` on a ``input_shape`` float32 input
    (batch size 1 recommended; the count is for the whole batch)."""
    x = jax.ShapeDtypeStruct(tuple(input_shape), jnp.float32)
    variables = jax.eval_shape(lambda v: module.init(jax.random.key(0), v, **apply_kwargs), x)
    total = [0]

    def interceptor(next_fun, args, kwargs, context):
        out = next_fun(*args, **kwargs)
        mod = context.module
        if context.method_name != "__call__":
            return out
        if isinstance(mod, nn.Conv | Conv2D):
            kernel = mod.variables["params"]["kernel"]
            kh, kw, cin_g, cout = kernel.shape
            total[0] += math.prod(out.shape[:-1]) * cout * kh * kw * cin_g
        elif isinstance(mod, DepthwiseConv):
            kernel = mod.variables["params"]["kernel"]
            kh, kw, _, c = kernel.shape
            total[0] += math.prod(out.shape[:-1]) * c * kh * kw
        elif isinstance(mod, nn.Dense):
            kernel = mod.variables["params"]["kernel"]
            cin, cout = kernel.shape
            total[0] += math.prod(out.shape[:-1]) * cin * cout
        return out

    def run(v, inp):
        with nn.intercept_methods(interceptor):
            return module.apply(v, inp, **apply_kwargs)

    jax.eval_shape(run, variables, x)
    return int(total[0])


def detector_counts(config) -> dict:
    """``{"params", "macs", "gflops"}`` of a detector at ``config.img_size``, batch 1."""
    from uavcal_jax.detect.model import build_detector

    h, w = config.img_size
    module = build_detector(config)
    x = jax.ShapeDtypeStruct((1, h, w, 3), jnp.float32)
    variables = jax.eval_shape(lambda v: module.init(jax.random.key(0), v), x)
    macs = count_macs(module, (1, h, w, 3))
    return {"params": count_params(variables), "macs": macs, "gflops": 2.0 * macs / 1e9}


def classifier_counts(num_classes: int = 20, size: int = 224) -> dict:
    """Counts of the classification YZNet (RPEOD Table 1) at ``size x size``."""
    from uavcal_jax.detect.yznet import YZNetClassifier

    module = YZNetClassifier(num_classes)
    x = jax.ShapeDtypeStruct((1, size, size, 3), jnp.float32)
    variables = jax.eval_shape(lambda v: module.init(jax.random.key(0), v), x)
    params = variables["params"]
    return {
        "params": count_params(params),
        "params_bn": int(
            sum(
                math.prod(v.shape)
                for path, v in jax.tree_util.tree_flatten_with_path(params)[0]
                if any(getattr(p, "key", None) == "bn" for p in path)
            )
        ),
        "macs": count_macs(module, (1, size, size, 3)),
    }
