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
torch's own products). ``fwk_vcconv`` calls every operator of this module through
``fwk.native.differentiable`` (the module's names below are those calls; ``<name>.op`` is the operator):
the same gradients without torch's per-call Python around a custom op (1.056x the chapter 5 width's
step, 27 of 40 rounds).

The ``kernel`` order (``kernel_product``, ``fwk_vcconv::kernel_product``) takes the explicit
kernels Wk (one c x o kernel per coefficient row, made by one product with the basis) and, per
output vertex, gathers its slots' input rows into a (b, K c) block and its kernels into (K c, o):
y_i = G_i W_i, one BLAS call, and the residual's average in the same pass; the backward gives
dW_i = G_i^T dy_i (to the kernels' rows) and dG_i = dy_i W_i^T (scattered to x's rows). It halves
the multiply-adds of the chapter 5 width's first layer (3 -> 8 channels), where it is the
fastest order.

A fourth operator, ``tall_product`` (``fwk_vcconv::tall_product``), does the products with the
basis that surround those kernels, where they are tall and narrow (``tall``): T (n_out b, c M) @
B (c M, o) in the ``sum`` order and x (n_in b, c) @ B (c, o M) in the ``basis`` order, 49,424 rows
by 8 x 105 in the chapter 5 width's outer layers. MKL runs these at 6-25 GFLOP/s on 2 threads
and its gradient A^T dC 6x slower than the same product transposed; ``fwk_native.h``'s
``tall_mm`` / ``tall_tn`` cut them into row blocks that stay in cache, one single-threaded BLAS
call each, the long side first (1.1-1.2x the chapter 5 width's training step; the thesis width's
wider bases stay with torch's product, which is as fast there). Where the lane kernels run, a product
whose result has at most 128 columns (the forward's N, the gradient dA's K) is ``tall_lanes`` instead:
each row of A broadcast against B's rows held as vectors, 8 or 4 rows at a time, no packing of A and
no scaling pass over C (MKL's copy and scaling routines were as many of the step's perf samples as its
products): 1.2-3.0x the BLAS calls on the chapter 5 width's products, 1.3-1.7x on the thesis width's
(10,096 x 1,120 x 64 and x 128, 59,623 x 35 x 96). The basis's gradient A^T dC stays with ``tall_tn``.

A fifth, ``basis_lanes`` (``fwk_vcconv::basis_lanes``), runs the whole ``basis`` order of a narrow
layer in one pass with the batch as the vector: a vertex's rows are taken 16 batch entries at a
time (one AVX-512 register of floats), Z_j = B^T x_j is made in cache instead of by a tall product,
and every per-vertex product is a multiply-add of whole registers whatever the channel counts
(3-16 at the chapter 5 width, where MKL runs the per-vertex products at 30-50 GFLOP/s and a plain
loop in registers at 100-140). Its backward makes dZ_j in cache the same way, dx_j and dB from it,
and dA with Z laid out kernels-innermost (the kernels as the vector, no horizontal sums: 16-float
vectors and, for the last 1-8 kernels, a half vector, ``KernelChunks``, so that M = 35 costs 2.5
vectors a row, not 3: Zen 4 runs a 16-float multiply-add as two halves). For layers
whose input vertices hold many slots of few channels (the chapter 5 width's 8 -> 3), the forward has
a second route with about half the multiply-adds, taken where the cost model prices it cheaper
(``lanes_forward_route``): each slot's kernel W_s = A_s B made in cache and applied to x_j. It adds
the layer's bias as the result leaves the lanes. Those
functions are compiled for AVX-512 only (``lanes``: False on other CPUs, where the tall product and
``basis_product`` run). ``kernel_lanes`` (``fwk_vcconv::kernel_lanes``) is ``kernel_product`` alike:
each slot's kernel applied to 16 batch entries a register, forward and the input's gradient (2x the
BLAS kernel's there); the kernels' gradient is a sum over the batch for each slot, made from the
batch-major rows two slots at a time (3.5x ``kernel_product``'s per-vertex BLAS call on the chapter 5
width's first layer, 1.04x its training step). ``sum_product``'s forward runs in lanes too (``sum_forward``
with ``lanes``: each T_i with the kernels as the vector, 1.2-2.0x the per-vertex BLAS call), and its
coefficients' gradient (1.3-1.6x), and x's gradient (``sum_vertex_lanes_dx``: dT_i transposed in 16 x 16
register blocks, the batch as the vector, six slots by four vectors at a time; 1.1-1.3x the per-vertex BLAS call
on the chapter 5 width's encoder, 1.03-1.5x on the thesis width's). All three together: 1.10-1.46x the
chapter 5 width's training step
(``benchmarks/training.py``, "no lanes", 2026-12-07). The lane kernels ask for the next vertex's
scattered rows while computing this one's (``fwk_native.h``'s ``prefetch_rows``).

Two small operators serve the residual's weighted average, r_i = sum_j w~_ij R x_j (w~ the weights
normalised over output i's support, sqrt(r) folded in): ``residual_weights`` (``fwk_vcconv::residual_weights``)
makes w~ in one pass per output vertex, forward and backward, instead of six torch ops each way, and
``weighted_rows`` (``fwk_vcconv::weighted_rows``) the ``basis`` order's average from the output side, each row
made from rows read in place (the backward's dx from the input side): no scatter, where ``basis_product`` with
one coefficient a slot needed per-thread accumulators and a BLAS call per vertex for products one column wide.

``elu_mix`` (``fwk_vcconv::elu_mix``, AVX-512: ``lanes()``) ends a residual block, y = sqrt(r) res + sqrt(1 - r)
ELU(t), in one pass, and its gradient in one (torch: ELU, the add and their gradients, four passes, and its ELU's
e^t - 1 at about 70 cycles a register, 1.2 ms of the chapter 5 width's step). e^t comes from Cephes' expf polynomial
and AVX-512's scalef (within about 1 ulp of torch's ELU, tested against float64); ``VCConv`` takes it for torch's
ELU with alpha 1 only (``_fused_elu``): 1.02x the chapter 5 width's step. A layer without an activation (the last of
fwk's encoders and decoders) takes its identity mix, res + a t, with the result laid out batch-major: the (b, n, c)
view the conv hands on is contiguous, so the decoder's copy into the loss's layout and the copy of the loss's
gradient back are gone (the chapter 5 width's last layer, in the step: 0.33 and 0.29 ms against 0.81 ms for torch's
add, the two copies and the gradient's product).

The kernels are float32 and compiled on first use (``fwk.native``: a C++ compiler and ninja;
about a minute, once per machine and torch version). ``available()`` is False when the build
fails (the reason is printed once, ``failed()``) or ``FWK_VCCONV_NATIVE=0``; ``usable()`` is
also False for other dtypes, devices and bf16 autocast; ``VCConv`` then runs its torch code.
Tested against per-vertex loops (``tall_product``: the dense product; ``basis_lanes``: the slot loop
with each slot's kernel) in float64, value and gradient (``tests/convs/test_vcconv_native.py``), and
the whole conv against the naive sum on both paths, every product with the basis on ``tall_product``
(``tests/autoencoders/test_vcconv_naive.py``).
"""
from __future__ import annotations

import functools
from pathlib import Path

import torch

from fwk.native import Extension, differentiable

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
    (r empty, (0,), when w is). x (n_in, B), coef (R, M), w (R) or (0,), src and pos (slots).
    Where the lane kernels run (``lanes``, M + 1 <= 64 with w), T_i is made with the kernels as the
    vector (``sum_forward`` with ``lanes``: 1.2-1.8x the per-vertex BLAS call on the chapter 5 width's
    encoder), and so are the backward's coefficients' gradients (1.3-1.6x their BLAS call) and x's gradient
    (dT_i transposed in registers, the batch as the vector: 1.1-1.3x)."""
    in_lanes = lanes(coef.shape[1] + (1 if w.shape[0] else 0))
    T, r = _load().sum_forward(x.contiguous(), coef.contiguous(), w.contiguous(), offs, src, pos, in_lanes)
    return T, r


@sum_product.register_fake
def _(x, coef, w, offs, src, pos):
    n_out, B = offs.shape[0] - 1, x.shape[1]
    return x.new_empty(n_out, B, coef.shape[1]), x.new_empty(n_out, B) if w.shape[0] else x.new_empty(0)


def _sum_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _residual_grad(dr, x, w, n_out):
    """The gradient of the residual's average r (n_out, B) as the kernels take it: zeros where autograd
    gives none, (0,) without residual weights w."""
    if not w.shape[0]:
        return x.new_empty(0)
    B = x.shape[1]
    return x.new_zeros(n_out, B) if dr is None or dr.shape != (n_out, B) else dr.contiguous()


def _sum_backward(ctx, dT, dr):
    x, coef, w, offs, src, pos = ctx.saved_tensors
    n_out, B = offs.shape[0] - 1, x.shape[1]
    dT = x.new_zeros(n_out, B, coef.shape[1]) if dT is None else dT.contiguous()
    dr = _residual_grad(dr, x, w, n_out)
    need = ctx.needs_input_grad
    in_lanes = lanes(coef.shape[1] + (1 if w.shape[0] else 0))  # the coefficients' gradient; dx by BLAS
    dx, dcoef, dw = _load().sum_backward(dT, dr, x.contiguous(), coef.contiguous(), w.contiguous(), offs, src, pos,
                                         need[0], need[1], need[2] and w.shape[0] > 0, in_lanes)
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


# ---- the residual's weighted average
@torch.library.custom_op("fwk_vcconv::weighted_rows", mutates_args=())
def weighted_rows(x: torch.Tensor, w: torch.Tensor, offs: torch.Tensor, src: torch.Tensor, pos: torch.Tensor,
                  in_offs: torch.Tensor, in_dst: torch.Tensor, in_pos: torch.Tensor) -> torch.Tensor:
    """r (n_out, B): r_i = sum_s w[pos[s]] x[src[s]] over output i's slots s in [offs[i], offs[i + 1])
    (the ``basis`` order's residual average), each row made from the rows read in place, no scatter.
    x (n_in, B), w (R), src and pos (slots). The same slots listed by input vertex (in_offs (n_in + 1),
    in_dst, in_pos) give the backward's dx_j = sum_s w[in_pos[s]] dr[in_dst[s]] without a scatter, and
    dw[pos[s]] = <dr_i, x[src[s]]>."""
    return _load().weighted_forward(x.contiguous(), w.contiguous(), offs, src, pos)


@weighted_rows.register_fake
def _(x, w, offs, src, pos, in_offs, in_dst, in_pos):
    return x.new_empty(offs.shape[0] - 1, x.shape[1])


def _weighted_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _weighted_backward(ctx, dr):
    x, w, offs, src, pos, in_offs, in_dst, in_pos = ctx.saved_tensors
    need_x, need_w = ctx.needs_input_grad[:2]
    dx, dw = _load().weighted_backward(dr.contiguous(), x.contiguous(), w.contiguous(), offs, src, pos, in_offs,
                                       in_dst, in_pos, need_x, need_w)
    return (dx if need_x else None), (dw if need_w else None), None, None, None, None, None, None


weighted_rows.register_autograd(_weighted_backward, setup_context=_weighted_setup)


@torch.library.custom_op("fwk_vcconv::residual_weights", mutates_args=())
def residual_weights(w: torch.Tensor, offs: torch.Tensor, pos: torch.Tensor, scale: float) -> torch.Tensor:
    """wn (R): wn[pos[s]] = scale |w[pos[s]]| / max(S_i, 1e-12), S_i = sum_s |w[pos[s]]| over output i's slots
    s in [offs[i], offs[i + 1]) (vcconv's normalised residual weights, ``VCConv._res_weights``), one pass
    per output vertex forward and backward; 0 at rows no slot names."""
    return _load().norm_weights_forward(w.contiguous(), offs, pos, scale)


@residual_weights.register_fake
def _(w, offs, pos, scale):
    return torch.empty_like(w)


def _norm_setup(ctx, inputs, output):
    w, offs, pos, scale = inputs
    ctx.save_for_backward(w, offs, pos)
    ctx.scale = scale


def _norm_backward(ctx, dwn):
    w, offs, pos = ctx.saved_tensors
    return _load().norm_weights_backward(dwn.contiguous(), w.contiguous(), offs, pos, ctx.scale), None, None, None


residual_weights.register_autograd(_norm_backward, setup_context=_norm_setup)


# ---- kernel order
@torch.library.custom_op("fwk_vcconv::kernel_product", mutates_args=())
def kernel_product(x: torch.Tensor, Wk: torch.Tensor, w: torch.Tensor, offs: torch.Tensor, src: torch.Tensor,
                   pos: torch.Tensor, b: int, c: int, o: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(y (n_out, b, o), r (n_out, b c)): y_i = sum_k x[src_k]^T W[pos_k] with the explicit kernels
    Wk (R, c o) (each row a c x o kernel), r_i = sum_k w[pos_k] x[src_k] (r empty, (0,), when w is),
    over output i's slots k in [offs[i], offs[i + 1]). x (n_in, b c), src and pos (slots)."""
    y, r = _load().kernel_forward(x.contiguous(), Wk.contiguous(), w.contiguous(), offs, src, pos, b, c, o)
    return y, r


@kernel_product.register_fake
def _(x, Wk, w, offs, src, pos, b, c, o):
    n_out = offs.shape[0] - 1
    return x.new_empty(n_out, b, o), x.new_empty(n_out, x.shape[1]) if w.shape[0] else x.new_empty(0)


def _kernel_setup(ctx, inputs, output):
    x, Wk, w, offs, src, pos, b, c, o = inputs
    ctx.save_for_backward(x, Wk, w, offs, src, pos)
    ctx.bco = (b, c, o)


def _kernel_backward(ctx, dy, dr):
    x, Wk, w, offs, src, pos = ctx.saved_tensors
    b, c, o = ctx.bco
    n_out = offs.shape[0] - 1
    dy = x.new_zeros(n_out, b, o) if dy is None else dy.contiguous()
    dr = _residual_grad(dr, x, w, n_out)
    need = ctx.needs_input_grad
    dx, dWk, dw = _load().kernel_backward(dy, dr, x.contiguous(), Wk.contiguous(), w.contiguous(), offs, src, pos,
                                          b, c, o, need[0], need[1], need[2] and w.shape[0] > 0)
    return (dx if need[0] else None), (dWk if need[1] else None), (dw if need[2] and w.shape[0] else None), \
        None, None, None, None, None, None


kernel_product.register_autograd(_kernel_backward, setup_context=_kernel_setup)


# ---- the products with the basis
#: ``tall_product`` is used where B has at most this many floats (and A at least TALL_MIN_ROWS rows):
#: the shapes MKL runs slowly. At the thesis width's 64 x 1120 and 128 x 2240 MKL's own blocking
#: is as fast or faster (measured 2026-12-06, ``benchmarks/training.py``)
TALL_MAX_B = 16384
TALL_MIN_ROWS = 4096


def tall(A: torch.Tensor, B: torch.Tensor) -> bool:
    """Whether ``tall_product`` takes the product A @ B (see ``TALL_MAX_B``)."""
    return A.shape[0] >= TALL_MIN_ROWS and B.numel() <= TALL_MAX_B


@torch.library.custom_op("fwk_vcconv::tall_product", mutates_args=())
def tall_product(A: torch.Tensor, B: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """C (R, N) = A (R, K) @ B (K, N) + bias (N; or (0,): none), for R large and K, N small. Where the
    lane kernels run (``lanes``) and the result has at most 128 columns: ``tall_lanes``, rows of A against
    B's rows as the vectors in registers, 1.2-3.0x the BLAS route on the chapter 5 width's products (MKL
    packed A and scaled C first on every block). Otherwise blocks of rows that stay in cache, one
    single-threaded BLAS call each, in parallel (``fwk_native.h``'s ``tall_mm``; MKL runs (49,424 x 8) @
    (8 x 105) at 6-25 GFLOP/s on 2 threads, its gradient A^T dC 6x slower than the same product
    transposed). The gradients: dA = dC B^T by the same route for its K columns, dB = A^T dC by BLAS,
    summed per thread in thread order, dbias = dC's column sums. Each row of C (and of dA) is the same
    bits on any thread count."""
    return _load().tall_forward(A.contiguous(), B.contiguous(), bias.contiguous(), lanes())


@tall_product.register_fake
def _(A, B, bias):
    return A.new_empty(A.shape[0], B.shape[1])


def _tall_setup(ctx, inputs, output):
    A, B, bias = inputs
    ctx.save_for_backward(A, B)
    ctx.has_bias = bias.shape[0] > 0


def _tall_backward(ctx, dC):
    A, B = ctx.saved_tensors
    need_A, need_B, need_bias = ctx.needs_input_grad
    dC = dC.contiguous()
    dA, dB = _load().tall_backward(dC, A.contiguous(), B.contiguous(), need_A, need_B, lanes())
    dbias = dC.sum(0) if need_bias and ctx.has_bias else None
    return (dA if need_A else None), (dB if need_B else None), dbias


tall_product.register_autograd(_tall_backward, setup_context=_tall_setup)


# ---- the basis order in lanes
def lanes(M: int = 1) -> bool:
    """Whether the lane kernels (``basis_lanes``, ``kernel_lanes``, ``sum_product``'s forward) run on
    this machine: the kernels enabled and built, a CPU with AVX-512F; and whether they take M kernels
    (at most 64; the sum order's residual counts as one)."""
    return 1 <= M <= 64 and available() and _cpu_runs_lanes()


@functools.cache
def _cpu_runs_lanes() -> bool:
    """The built module's answer (its lane functions are compiled for AVX-512; asked once)."""
    return bool(_load().lanes_supported())


@torch.library.custom_op("fwk_vcconv::basis_lanes", mutates_args=())
def basis_lanes(x: torch.Tensor, basis: torch.Tensor, coef: torch.Tensor, offs: torch.Tensor, dst: torch.Tensor,
                pos: torch.Tensor, n_out: int, bias: torch.Tensor) -> torch.Tensor:
    """y (n_out, b, o): the ``basis`` order in one pass, the batch as the vector (``native.cpp``,
    "the basis order in lanes"): for input vertex j, Z_j = B^T x_j in cache, and each of its slots s
    adds A_s Z_j (A_s = coef[pos[s]]) at dst[s]. x (n_in, b, c), basis (M, c, o), coef (R, M), offs
    (n_in + 1), dst and pos (slots); bias (o) added as the result leaves the lanes (no pass of its own), or
    (0,): none."""
    M, c, o = basis.shape
    route = LANES_FORWARD or lanes_forward_route(x.shape[0], dst.shape[0], x.shape[1], c, o, M)
    return _load().lanes_forward(x.contiguous(), basis.contiguous(), coef.contiguous(), offs, dst, pos, n_out,
                                 bias.contiguous(), route)


#: ``basis_lanes``' forward route (``native.cpp``, ``lanes_forward``): 1 through Z_j = B^T x_j per input vertex, 2
#: through each slot's kernel W_s = A_s B (layers with c o <= 64), 0 the cheaper by ``lanes_forward_route``
#: (tests force each)
LANES_FORWARD = 0
#: the price of route 2's multiply-adds in route 1's: route 2 ran at about 0.7 of route 1's rate per multiply-add
#: (measured 2026-12-07 on the chapter 5 width's 8 -> 3 layer, 2 threads, batch 16: 2.66 against 3.56 ms at 0.52 of
#: the multiply-adds)
LANES_FORWARD_W_PRICE = 1.4


def lanes_forward_route(n_in: int, slots: int, b: int, c: int, o: int, M: int) -> int:
    """``basis_lanes``' cheaper forward route for a layer (``LANES_FORWARD``): 1 costs n_in M o c L' + slots M o L'
    multiply-adds (L' = b rounded up to 16: the lanes), 2 costs slots G (M c o + 16 c o) (G = L' / 16: each slot's
    kernel made once a group of 16 batch entries), priced at ``LANES_FORWARD_W_PRICE``; 2 only where c o <= 64."""
    lanes_b = -(-b // 16) * 16
    via_z = n_in * M * o * c * lanes_b + slots * M * o * lanes_b
    via_w = slots * (lanes_b // 16) * (M * c * o + c * o * 16)
    return 2 if c * o <= 64 and LANES_FORWARD_W_PRICE * via_w < via_z else 1


@basis_lanes.register_fake
def _(x, basis, coef, offs, dst, pos, n_out, bias):
    return x.new_empty(n_out, x.shape[1], basis.shape[2])


def _lanes_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs[:6])  # x, basis, coef, offs, dst, pos (not n_out, not the bias)


def _lanes_backward(ctx, dy):
    x, basis, coef, offs, dst, pos = ctx.saved_tensors
    need_x, need_B, need_c = ctx.needs_input_grad[:3]
    need_bias = ctx.needs_input_grad[7]  # made as dy goes into lanes, not by a pass of its own (_bias_grad)
    dx, dB, dcoef, dbias = _load().lanes_backward(dy.contiguous(), x.contiguous(), basis.contiguous(),
                                                  coef.contiguous(), offs, dst, pos, need_x, need_B, need_c, need_bias)
    return (dx if need_x else None), (dB if need_B else None), (dcoef if need_c else None), None, None, None, None, \
        (dbias if need_bias else None)


def _bias_grad(dy):
    """A bias's gradient from the result's, dy (n, b, o): its sum over vertices and batch."""
    return dy.sum((0, 1))


basis_lanes.register_autograd(_lanes_backward, setup_context=_lanes_setup)


@torch.library.custom_op("fwk_vcconv::kernel_lanes", mutates_args=())
def kernel_lanes(x: torch.Tensor, Wk: torch.Tensor, w: torch.Tensor, offs: torch.Tensor, src: torch.Tensor,
                 pos: torch.Tensor, o: int, bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(y (n_out, b, o), r (n_out, b, c)): ``kernel_product`` with the batch as the vector (``native.cpp``,
    "kernel order in lanes"): y_i = bias + sum_s x_src[s] W_pos[s] and r_i = sum_s w_pos[s] x_src[s] (r empty,
    (0,), when w is; bias (o) or (0,): none), each slot's kernel (a row of Wk, c x o) applied to 16 batch entries a
    register. x (n_in, b, c). Its gradient for x in lanes as well, for Wk and w from the batch-major rows."""
    y, r = _load().kernel_lanes_forward(x.contiguous(), Wk.contiguous(), w.contiguous(), offs, src, pos, o,
                                        bias.contiguous())
    return y, r


@kernel_lanes.register_fake
def _(x, Wk, w, offs, src, pos, o, bias):
    n_out, b, c = offs.shape[0] - 1, x.shape[1], x.shape[2]
    return x.new_empty(n_out, b, o), x.new_empty(n_out, b, c) if w.shape[0] else x.new_empty(0)


def _kernel_lanes_setup(ctx, inputs, output):
    x, Wk, w, offs, src, pos, o, _ = inputs
    ctx.save_for_backward(x, Wk, w, offs, src, pos)
    ctx.o = o


def _kernel_lanes_backward(ctx, dy, dr):
    x, Wk, w, offs, src, pos = ctx.saved_tensors
    (_, b, c), o, n_out = x.shape, ctx.o, offs.shape[0] - 1
    dy = x.new_zeros(n_out, b, o) if dy is None else dy.contiguous()
    if w.shape[0]:
        dr = x.new_zeros(n_out, b, c) if dr is None else dr.contiguous()
    else:
        dr = x.new_empty(0)
    need = ctx.needs_input_grad
    x = x.contiguous()
    dx, dWk, dw = _load().kernel_lanes_backward(dy, dr, x, Wk.contiguous(), w.contiguous(), offs, src, pos, need[0],
                                                need[1], need[2] and w.shape[0] > 0)
    return (dx if need[0] else None), (dWk if need[1] else None), (dw if need[2] and w.shape[0] else None), \
        None, None, None, None, (_bias_grad(dy) if need[7] else None)


kernel_lanes.register_autograd(_kernel_lanes_backward, setup_context=_kernel_lanes_setup)


@torch.library.custom_op("fwk_vcconv::elu_mix", mutates_args=())
def elu_mix(t: torch.Tensor, res: torch.Tensor, a: float, elu: bool, batch_major: bool) -> torch.Tensor:
    """The residual block's activation and mix in one pass (``native.cpp``, AVX-512 only: ``lanes()``):
    res + a f(t), or f(t) where res is empty ((0,)); f = ELU (``elu``) or the identity (a network's last layer);
    t and res of one shape. ELU's e^t - 1 from Cephes' polynomial (about 1 ulp from torch's); the gradient
    a g f'(t) for t, g itself for res. ``batch_major`` (t (n, b, c)): the result laid out as (b, n, c) (strides
    (c, n c, 1)), so that the conv's transposed view of it is contiguous and the loss's gradient comes back
    through the backward without a copy either way."""
    return _load().elu_mix_forward(t.contiguous(), res.contiguous(), a, elu, batch_major)


@elu_mix.register_fake
def _(t, res, a, elu, batch_major):
    if batch_major:
        n, b, c = t.shape
        return torch.empty_strided((n, b, c), (c, n * c, 1), dtype=t.dtype, device=t.device)
    return t.new_empty(t.shape)


def _elu_mix_setup(ctx, inputs, output):
    t, res, a, elu, _ = inputs
    if elu:
        ctx.save_for_backward(t)
    ctx.has_res, ctx.elu = res.numel() > 0, elu
    ctx.a = a if ctx.has_res else 1.0


def _elu_mix_backward(ctx, g):
    need_t, need_res = ctx.needs_input_grad[:2]
    need_res = need_res and ctx.has_res
    t = ctx.saved_tensors[0].contiguous() if ctx.elu else g.new_empty(0)
    dt, dres = _load().elu_mix_backward(g, t, ctx.a, ctx.elu, need_t, need_res)
    # res's gradient is g itself, made in t's layout only where g came batch-major
    return (dt if need_t else None), ((dres if dres.numel() else g) if need_res else None), None, None, None


elu_mix.register_autograd(_elu_mix_backward, setup_context=_elu_mix_setup)


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

    @register_flop_formula(torch.ops.fwk_vcconv.weighted_rows)
    def _weighted_flops(x_shape, w_shape, offs_shape, src_shape, *args, out_shape=None, **kwargs) -> int:
        return 2 * src_shape[0] * x_shape[1]  # as basis_product with one coefficient a slot, which it replaced

    @register_flop_formula(torch.ops.fwk_vcconv.kernel_product)
    def _kernel_flops(x_shape, Wk_shape, w_shape, offs_shape, src_shape, pos_shape, b, c, o, *args, out_shape=None,
                      **kwargs) -> int:
        return 2 * src_shape[0] * b * c * (o + (1 if w_shape[0] else 0))

    @register_flop_formula(torch.ops.fwk_vcconv.tall_product)
    def _tall_flops(A_shape, B_shape, bias_shape, *args, out_shape=None, **kwargs) -> int:
        return 2 * A_shape[0] * A_shape[1] * B_shape[1]

    @register_flop_formula(torch.ops.fwk_vcconv.basis_lanes)
    def _lanes_flops(x_shape, basis_shape, coef_shape, offs_shape, dst_shape, pos_shape, n_out, *args, out_shape=None,
                     **kwargs) -> int:
        (n_in, b, c), (M, _, o) = x_shape, basis_shape  # the basis product and the per-slot products, as in basis
        return 2 * n_in * b * c * M * o + 2 * dst_shape[0] * M * b * o

    @register_flop_formula(torch.ops.fwk_vcconv.kernel_lanes)
    def _kernel_lanes_flops(x_shape, Wk_shape, w_shape, offs_shape, src_shape, pos_shape, o, *args, out_shape=None,
                            **kwargs) -> int:
        _, b, c = x_shape  # as kernel_product
        return 2 * src_shape[0] * b * c * (o + (1 if w_shape[0] else 0))


_register_flops()

# What fwk_vcconv calls: each operator behind ``fwk.native.differentiable``, the same values and gradients for
# about 40 us less a call (31 calls a step at the chapter 5 width); the operator itself is ``<name>.op``
# (``torch.ops.fwk_vcconv.<name>``, differentiable as well)
(sum_product, basis_product, weighted_rows, residual_weights, kernel_product, tall_product, basis_lanes, kernel_lanes,
 elu_mix) = (differentiable(op) for op in (sum_product, basis_product, weighted_rows, residual_weights, kernel_product,
                                           tall_product, basis_lanes, kernel_lanes, elu_mix))
