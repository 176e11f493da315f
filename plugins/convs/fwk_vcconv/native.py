"""vcconv's per-vertex products as native kernels (``native.cpp``), with their gradients.

The two evaluation orders of ``VCConv`` that dominate a step, in torch, materialise one row per
support slot: ``sum`` gathers the input rows (slots x b c floats; 51 MB in the thesis-width
VAE's second encoder layer) before a padded batched product, and ``basis`` writes each slot's
product (slots x b c_out) before a scatter-add; their backward passes do it again, and every
fresh buffer faults its pages in. The kernels in ``native.cpp`` do the same sums vertex by
vertex on the exact support (no padding, no mask): a vertex's rows are gathered into a buffer
that stays in cache, multiplied by one BLAS call, and accumulated into the result (per-thread
accumulators for the scatters, summed in thread order).

    sum order:    T_i = X_i^T A_i,  r_i = X_i^T a_i     X_i = x[src[s]], A_i = coef[pos[s]], a_i = w[pos[s]]
    basis order:  y_o = sum_{s: dst[s] = o} (A_j Z_j^T)[s]           A_j = coef[pos[s]], s in slots(j)

with the gradients dX_i = A_i dT_i^T (+ a_i dr_i^T; scattered to x's rows), dA_i = X_i dT_i, and
dA_j = dY_j Z_j, dZ_j = dY_j^T A_j (dY_j = dy's rows at dst). The coefficients are read in place
(``pos``: each slot's row of the conv's coefficients, each named once) and their gradients
written there: no gathered copy of them, no scatter-add back. ``sum_product`` and
``basis_product`` are ``torch.library`` operators (``fwk_vcconv::sum_product``,
``fwk_vcconv::basis_product``) with these gradients registered, and with their multiply-adds
registered for ``torch.utils.flop_counter`` (so the training benchmark counts them as it counts
torch's own products).

The kernels are float32 and compiled on first use (``fwk.native``: a C++ compiler and ninja;
about a minute, once per machine and torch version). ``available()`` is False when the build
fails (the reason is printed once, ``failed()``) or ``FWK_VCCONV_NATIVE=0``; ``usable()`` is
also False for other dtypes, devices and bf16 autocast; ``VCConv`` then runs its torch code.
Tested against per-vertex loops in float64, value and gradient
(``tests/convs/test_vcconv_native.py``), and the whole conv against the naive sum on both paths
(``tests/autoencoders/test_vcconv_naive.py``).
"""
from __future__ import annotations

from pathlib import Path

import torch

from fwk.native import Extension

KERNELS = Extension("fwk_vcconv_native", [Path(__file__).with_name("native.cpp")], label=__package__,
                    env="FWK_VCCONV_NATIVE")
enabled, available, usable = KERNELS.enabled, KERNELS.available, KERNELS.usable
_load = KERNELS.load


def failed() -> str | None:
    """Why the kernels did not build (None when they did, or were not tried yet)."""
    return KERNELS.failed


# ---- sum order
@torch.library.custom_op("fwk_vcconv::sum_product", mutates_args=())
def sum_product(x: torch.Tensor, coef: torch.Tensor, w: torch.Tensor, offs: torch.Tensor, src: torch.Tensor,
                pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(T (n_out, B, M), r (n_out, B)): T_i = X_i^T A_i, r_i = X_i^T a_i, with A_i the rows
    coef[pos[s]] and a_i the weights w[pos[s]] of output i's slots s in [offs[i], offs[i + 1])
    (r empty, (0,), when w is). x (n_in, B), coef (R, M), w (R) or (0,), src and pos (slots)."""
    T, r = _load().sum_forward(x.contiguous(), coef.contiguous(), w.contiguous(), offs, src, pos)
    return T, r


@sum_product.register_fake
def _(x, coef, w, offs, src, pos):
    n_out, B = offs.shape[0] - 1, x.shape[1]
    return x.new_empty(n_out, B, coef.shape[1]), x.new_empty(n_out, B) if w.shape[0] else x.new_empty(0)


def _sum_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _sum_backward(ctx, dT, dr):
    x, coef, w, offs, src, pos = ctx.saved_tensors
    n_out, B = offs.shape[0] - 1, x.shape[1]
    dT = x.new_zeros(n_out, B, coef.shape[1]) if dT is None else dT.contiguous()
    if w.shape[0]:
        dr = x.new_zeros(n_out, B) if dr is None or dr.shape != (n_out, B) else dr.contiguous()
    else:
        dr = x.new_empty(0)
    need = ctx.needs_input_grad
    dx, dcoef, dw = _load().sum_backward(dT, dr, x.contiguous(), coef.contiguous(), w.contiguous(), offs, src, pos,
                                         need[0], need[1], need[2] and w.shape[0] > 0)
    return (dx if need[0] else None), (dcoef if need[1] else None), (dw if need[2] and w.shape[0] else None), \
        None, None, None


sum_product.register_autograd(_sum_backward, setup_context=_sum_setup)


# ---- basis order
@torch.library.custom_op("fwk_vcconv::basis_product", mutates_args=())
def basis_product(Z: torch.Tensor, coef: torch.Tensor, offs: torch.Tensor, dst: torch.Tensor, pos: torch.Tensor,
                  n_out: int) -> torch.Tensor:
    """y (n_out, B): y_o = sum of the slots' rows (A_j Z_j^T)[s] with dst[s] = o, A_j the rows
    coef[pos[s]] of input j's slots s in [offs[j], offs[j + 1]). Z (n_in, B, M), coef (R, M), dst
    and pos (slots)."""
    return _load().basis_forward(Z.contiguous(), coef.contiguous(), offs, dst, pos, n_out)


@basis_product.register_fake
def _(Z, coef, offs, dst, pos, n_out):
    return Z.new_empty(n_out, Z.shape[1])


def _basis_setup(ctx, inputs, output):
    Z, coef, offs, dst, pos, n_out = inputs
    ctx.save_for_backward(Z, coef, offs, dst, pos)


def _basis_backward(ctx, dy):
    Z, coef, offs, dst, pos = ctx.saved_tensors
    need_Z, need_c = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
    dZ, dcoef = _load().basis_backward(dy.contiguous(), Z.contiguous(), coef.contiguous(), offs, dst, pos,
                                       need_Z, need_c)
    return (dZ if need_Z else None), (dcoef if need_c else None), None, None, None, None


basis_product.register_autograd(_basis_backward, setup_context=_basis_setup)


# ---- multiply-adds for torch.utils.flop_counter (2 flops each)
def _register_flops():
    from torch.utils.flop_counter import register_flop_formula

    @register_flop_formula(torch.ops.fwk_vcconv.sum_product)
    def _sum_flops(x_shape, coef_shape, w_shape, offs_shape, src_shape, pos_shape, *args, out_shape=None,
                   **kwargs) -> int:
        return 2 * src_shape[0] * x_shape[1] * (coef_shape[1] + (1 if w_shape[0] else 0))

    @register_flop_formula(torch.ops.fwk_vcconv.basis_product)
    def _basis_flops(Z_shape, coef_shape, offs_shape, dst_shape, pos_shape, n_out, *args, out_shape=None,
                     **kwargs) -> int:
        return 2 * dst_shape[0] * Z_shape[1] * Z_shape[2]


_register_flops()
