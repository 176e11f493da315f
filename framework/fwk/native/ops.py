"""fwk's own native kernels (``core.cpp``), for what every training step does around its networks:

* ``swap01(x)``: ``x.transpose(0, 1).contiguous()``, the copy between a batch-major (b, n, c) tensor and
  the vertex-major (n, b, c) layout that vcconv's native kernels compute in (its input before the first
  layer, its result after the last, and that result's gradient). torch's copy of the transposed view runs
  its innermost loop over the 3 floats of a vertex: 0.27 ms for (16, 11,248, 3) floats on 2 threads,
  against 0.03 ms for a plain copy of as many floats; ``core.cpp`` copies tile by tile.
* ``l1_mean(a, b)``: the L1 loss ``mean |a - b|`` (thesis table 3.2) in one pass forward
  and one backward (g / N sgn(a - b)), where torch writes a - b, |a - b|, the expanded g / N, sgn(a - b)
  and their product: 1.3 ms of torch's operators for (16, 11,248, 3) floats in the chapter 5 width's
  step. Its gradient is the same floats as torch's (each a product of g / N and -1, 0 or 1); its
  value is summed in double over float blocks, so it may differ from torch's mean in the last bits.

Both are ``torch.library`` operators (``fwk::swap01``, ``fwk::l1_mean``) with their gradients registered,
called through ``fwk.native.differentiable``, and both fall back to the torch expression above where the
kernels do not apply (``FWK_CORE_NATIVE=0``, no compiler, autocast, another dtype or device, shapes that
differ: broadcasting is torch's). Together with vcconv's use of ``swap01`` they made the chapter 5 width's
training step 1.02x faster (``docs/methods/autoencoders.md`` "Speed", session 31).
"""
from __future__ import annotations

from pathlib import Path

import torch

from fwk.native import Extension, differentiable

CORE = Extension("fwk_core_native", [Path(__file__).with_name("core.cpp")], label="fwk", env="FWK_CORE_NATIVE")


@torch.library.custom_op("fwk::swap01", mutates_args=())
def _swap01(x: torch.Tensor) -> torch.Tensor:
    """x (A, B, C) -> (B, A, C), contiguous."""
    return CORE.load().swap01(x.contiguous())


@_swap01.register_fake
def _(x):
    return x.new_empty(x.shape[1], x.shape[0], x.shape[2])


def _swap01_setup(ctx, inputs, output):
    pass


def _swap01_backward(ctx, g):
    return CORE.load().swap01(g.contiguous())


_swap01.register_autograd(_swap01_backward, setup_context=_swap01_setup)


@torch.library.custom_op("fwk::l1_mean", mutates_args=())
def _l1_mean(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """mean |a - b| (a 0-d tensor), a and b of one shape."""
    return CORE.load().l1_mean(a.contiguous(), b.contiguous())


@_l1_mean.register_fake
def _(a, b):
    return a.new_empty(())


def _l1_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _l1_backward(ctx, g):
    a, b = ctx.saved_tensors
    need_a, need_b = ctx.needs_input_grad
    # g / N as torch's mean divides it (a float32 division), then g / N sgn(a - b) element by element
    da = CORE.load().l1_grad(a.contiguous(), b.contiguous(), g / a.numel())
    return (da if need_a else None), (-da if need_b else None)


_l1_mean.register_autograd(_l1_backward, setup_context=_l1_setup)

_swap01_call, _l1_mean_call = differentiable(_swap01), differentiable(_l1_mean)


def swap01(x: torch.Tensor) -> torch.Tensor:
    """``x.transpose(0, 1).contiguous()`` for a 3-dimensional x (differentiable): the native tile copy where x is a
    contiguous float32 CPU tensor and the kernels are usable, torch's copy otherwise."""
    if x.dim() == 3 and x.is_contiguous() and x.numel() and CORE.usable(x):
        return _swap01_call(x)
    return x.transpose(0, 1).contiguous()


def batch_major(y: torch.Tensor) -> torch.Tensor:
    """A network's (b, n, c) result as a contiguous tensor: y itself where it is; where y is a transposed view of
    vertex-major (n, b, c) memory (vcconv's native kernels compute vertex-major and hand on such a view), the copy
    ``swap01`` makes, whose gradient goes back vertex-major (so the conv has nothing to copy on its way back);
    ``y.contiguous()`` otherwise. The decoders hand on their result this way: the loss's and the metrics'
    elementwise operations on a strided view of 3 floats a vertex run 5-15x slower (the L1 loss's subtraction
    0.8 ms against 0.055 ms contiguous in the chapter 5 width's step)."""
    if y.is_contiguous():
        return y
    v = y.transpose(0, 1) if y.dim() == 3 else y
    return swap01(v) if y.dim() == 3 and v.is_contiguous() else y.contiguous()


def l1_mean(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The L1 loss ``mean |a - b|`` (differentiable in a and b): the native pass where a and b have one shape and are
    float32 CPU tensors and the kernels are usable, ``torch.abs(a - b).mean()`` otherwise (broadcasting, autocast,
    other dtypes and devices)."""
    if a.shape == b.shape and a.numel() and CORE.usable(a, b):
        return _l1_mean_call(a, b)
    return torch.abs(a - b).mean()
