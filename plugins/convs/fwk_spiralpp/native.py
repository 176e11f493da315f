"""SpiralNet++'s gather and product as a native kernel (``native.cpp``), with its gradient.

    y_i = W [x_{s(i,1)} || ... || x_{s(i,L)}] + b,    x (n_in, b, c) vertex-major, W (o, L c)

``GatherLinear``'s sums (same blocks of output vertices, same products) with the gathers and
scatters in C++: a block's spiral rows are copied into a buffer that stays in cache and one BLAS
call multiplies them; the backward gathers again for dW = dY^T G and scatters dG = dY W to dx,
through per-thread accumulators summed in thread order (the same bits on every run with a given
thread count). In torch the same work is an ``index_select`` of c-float rows per block (slow for
the 3-16 channels of a face network's outer layers), a product, and an ``index_add_`` per block,
dispatched from Python in worker threads.

And the conv of an up-sampled input (``SpiralPP.forward_up``, the decoder's fused pooling):

    y_i = b + sum_{(l, j, u) in row i of S} u Z_l[j],    Z_l = x W_l^T on the coarse vertices

the L products and the sparse sum y = S Z in C++ (``up_linear``; the torch code is
``PerEntryLinear`` and ``UpGather``, whose CSR product zero-fills and copies its output), and its
backward dZ = S^T dy row by row (no accumulators), dx = sum_l dZ_l W_l, dW_l = dZ_l^T x.

The products with a narrow result (an outer layer's 3-9 output channels) are computed with the
long side first and transposed in cache (``fwk_native.h``'s ``rows_gemm``), and ``up_linear``'s
L products over all n_c b rows in cache-sized row blocks (``tall_mm``, ``tall_tn``): BLAS
vectorises along its result's first dimension, which was o = 3 (the main job's PB network 1.05x
a step on 1 thread, 1.1-1.2x on 2).

``gather_linear`` and ``up_linear`` are ``torch.library`` operators (``fwk_spiralpp::gather_linear``,
``fwk_spiralpp::up_linear``) with their gradients and their multiply-adds registered (``torch.utils.flop_counter`` counts it as it counted
the torch code's products). Float32 on the CPU, compiled on first use (``fwk.native``);
``FWK_SPIRALPP_NATIVE=0``, bf16 autocast, float64 and CUDA take the torch code. Tested against
the naive per-vertex sums in float64 and against the torch code, value and gradient, on 1 and 2
threads (``tests/convs/test_spiralpp_native.py``).
"""
from __future__ import annotations

from pathlib import Path

import torch

from fwk.native import Extension, differentiable

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


@torch.library.custom_op("fwk_spiralpp::up_linear", mutates_args=())
def up_linear(x: torch.Tensor, weight_per_entry: torch.Tensor, bias: torch.Tensor, crow: torch.Tensor, col: torch.Tensor,
              val: torch.Tensor, t_crow: torch.Tensor, t_col: torch.Tensor, t_val: torch.Tensor,
              length: int) -> torch.Tensor:
    """y (n, b, o) = S Z + bias with Z (n_c, b, L, o), Z[j, s, l] = W_l x[j, s]: the conv of an
    up-sampled input (``SpiralPP.forward_up``). x (n_c, b, c); weight_per_entry (L o, c), row
    l o + p holding W[p, l c : (l + 1) c] (``per_entry``); bias (o,) or (0,); S (n, L n_c) as CSR
    (crow, col, val), column l n_c + j, and S^T alike (t_crow, t_col, t_val)."""
    return KERNELS.load().up_linear_forward(x.contiguous(), weight_per_entry.contiguous(), bias.contiguous(), crow,
                                            col, val, length)


@up_linear.register_fake
def _(x, weight_per_entry, bias, crow, col, val, t_crow, t_col, t_val, length):
    return x.new_empty(crow.shape[0] - 1, x.shape[1], weight_per_entry.shape[0] // length)


def _up_setup(ctx, inputs, output):
    x, Wp, bias, crow, col, val, t_crow, t_col, t_val, length = inputs
    ctx.save_for_backward(x, Wp, t_crow, t_col, t_val)
    ctx.length, ctx.has_bias = length, bias.numel() > 0


def _up_backward(ctx, dy):
    x, Wp, t_crow, t_col, t_val = ctx.saved_tensors
    need_x, need_w, need_b = ctx.needs_input_grad[:3]
    dx, dWp = KERNELS.load().up_linear_backward(dy.contiguous(), x.contiguous(), Wp.contiguous(), t_crow, t_col,
                                                t_val, ctx.length, need_x, need_w)
    db = dy.sum((0, 1)) if ctx.has_bias and need_b else None
    return (dx if need_x else None), (dWp if need_w else None), db, None, None, None, None, None, None, None


up_linear.register_autograd(_up_backward, setup_context=_up_setup)


def per_entry(weight: torch.Tensor, length: int) -> torch.Tensor:
    """The conv's weight (o, L c) laid out per spiral entry, (L o, c) (differentiable)."""
    o, Lc = weight.shape
    return weight.view(o, length, Lc // length).transpose(0, 1).reshape(length * o, Lc // length)


def _register_flops():
    from torch.utils.flop_counter import register_flop_formula

    @register_flop_formula(torch.ops.fwk_spiralpp.gather_linear)
    def _flops(x_shape, w_shape, b_shape, index_shape, *args, out_shape=None, **kwargs) -> int:
        return 2 * index_shape[0] * x_shape[1] * w_shape[0] * w_shape[1]

    @register_flop_formula(torch.ops.fwk_spiralpp.up_linear)
    def _up_flops(x_shape, w_shape, *args, out_shape=None, **kwargs) -> int:
        return 2 * x_shape[0] * x_shape[1] * x_shape[2] * w_shape[0]  # the dense product; S's sums left out, as before


_register_flops()

# What fwk_spiralpp calls: each operator behind ``fwk.native.differentiable``, the same values and gradients for
# about 40 us less a call; the operator itself is ``<name>.op`` (``torch.ops.fwk_spiralpp.<name>``)
gather_linear, up_linear = differentiable(gather_linear), differentiable(up_linear)
