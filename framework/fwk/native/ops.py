"""fwk's own native kernels (``core.cpp``), for what every training step does around its networks:
``l1_mean(a, b)``, the L1 loss ``mean |a - b|`` (thesis table 3.2), in one pass forward and one backward
(g / N sgn(a - b)), where torch writes a - b, |a - b|, the expanded g / N, sgn(a - b) and their product:
about 1.2 ms of torch's operators for (16, 11,248, 3) floats in the chapter 5 width's step. Its gradient is
the same floats as torch's (each a product of g / N and -1, 0 or 1; tested), so a training takes the same
steps; its value is summed in double over float blocks, and may differ from torch's mean in the last bit.

It is a ``torch.library`` operator (``fwk::l1_mean``) with its gradient registered, called through
``fwk.native.differentiable``, and falls back to ``torch.abs(a - b).mean()`` where the kernel does not apply
(``FWK_CORE_NATIVE=0``, no compiler, autocast, another dtype or device, shapes that differ: broadcasting is
torch's).
"""
from __future__ import annotations

from pathlib import Path

import torch

from fwk.native import Extension, differentiable

CORE = Extension("fwk_core_native", [Path(__file__).with_name("core.cpp")], label="fwk", env="FWK_CORE_NATIVE")


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

_l1_mean_call = differentiable(_l1_mean)


def l1_mean(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The L1 loss ``mean |a - b|`` (differentiable in a and b): the native pass where a and b have one shape and are
    float32 CPU tensors and the kernels are usable, ``torch.abs(a - b).mean()`` otherwise (broadcasting, autocast,
    other dtypes and devices)."""
    if a.shape == b.shape and a.numel() and CORE.usable(a, b):
        return _l1_mean_call(a, b)
    return torch.abs(a - b).mean()
