"""SpiralNet++'s gather and product as a native kernel (``native.cpp``), with its gradient.

    y_i = W [x_{s(i,1)} || ... || x_{s(i,L)}] + b,    x (n_in, b, c) vertex-major, W (o, L c)

``GatherLinear``'s sums (same blocks of output vertices, same products) with the gathers and
scatters in C++: a block's spiral rows are copied into a buffer that stays in cache and one BLAS
call multiplies them; the backward gathers again for dW = dY^T G and scatters dG = dY W to dx,
through per-thread accumulators summed in thread order (the same bits on every run with a given
thread count). In torch the same work is an ``index_select`` of c-float rows per block (slow for
the 3-16 channels of a face network's outer layers), a product, and an ``index_add_`` per block,
dispatched from Python in worker threads.

``gather_linear`` is a ``torch.library`` operator (``fwk_spiralpp::gather_linear``) with its
gradient and its multiply-adds registered (``torch.utils.flop_counter`` counts it as it counted
the torch code's products). Float32 on the CPU, compiled on first use (``fwk.native``);
``FWK_SPIRALPP_NATIVE=0``, bf16 autocast, float64 and CUDA take ``GatherLinear``. Tested against
the naive per-vertex sum in float64 and against ``GatherLinear``, value and gradient, on 1 and 2
threads (``tests/convs/test_spiralpp_native.py``).
"""
from __future__ import annotations

from pathlib import Path

import torch

from fwk.native import Extension

KERNELS = Extension("fwk_spiralpp_native", [Path(__file__).with_name("native.cpp")], label=__package__,
                    env="FWK_SPIRALPP_NATIVE")
enabled, available, usable = KERNELS.enabled, KERNELS.available, KERNELS.usable


def failed() -> str | None:
    """Why the kernel did not build (None when it did, or was not tried yet)."""
    return KERNELS.failed


@torch.library.custom_op("fwk_spiralpp::gather_linear", mutates_args=())
def gather_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """y (n_out, b, o): y_i = W [x_{index[i, 0]} || ... || x_{index[i, L-1]}] + bias. x (n_in, b, c),
    weight (o, L c), bias (o,) or (0,) for none, index (n_out, L) int64."""
    return KERNELS.load().gather_linear_forward(x.contiguous(), weight.contiguous(), bias.contiguous(),
                                                index.contiguous())


@gather_linear.register_fake
def _(x, weight, bias, index):
    return x.new_empty(index.shape[0], x.shape[1], weight.shape[0])


def _setup(ctx, inputs, output):
    x, weight, bias, index = inputs
    ctx.save_for_backward(x, weight, index)
    ctx.has_bias = bias.numel() > 0


def _backward(ctx, gy):
    x, weight, index = ctx.saved_tensors
    need_x, need_w, need_b = ctx.needs_input_grad[:3]
    dx, dW = KERNELS.load().gather_linear_backward(gy.contiguous(), x.contiguous(), weight.contiguous(),
                                                   index.contiguous(), need_x, need_w)
    db = gy.sum((0, 1)) if ctx.has_bias and need_b else None
    return (dx if need_x else None), (dW if need_w else None), db, None


gather_linear.register_autograd(_backward, setup_context=_setup)


def _register_flops():
    from torch.utils.flop_counter import register_flop_formula

    @register_flop_formula(torch.ops.fwk_spiralpp.gather_linear)
    def _flops(x_shape, w_shape, b_shape, index_shape, *args, out_shape=None, **kwargs) -> int:
        return 2 * index_shape[0] * x_shape[1] * w_shape[0] * w_shape[1]


_register_flops()
