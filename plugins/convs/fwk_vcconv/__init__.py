"""Conv ``vcconv``: the spatially varying convolution of the fully convolutional mesh
autoencoder (Zhou et al. 2020, "Fully Convolutional Mesh Autoencoder using Efficient Spatially
Varying Kernels"; thesis 3.3, 3.4, appendix A).

A global basis of M kernels B_m (c_in x c_out, ``weight_num`` = M, thesis: 35) is shared by the
whole mesh; each output vertex i has its own sampling coefficients A_ijm for every vertex j of
its neighbourhood N(i), so the kernel W_ij = sum_m A_ijm B_m varies over the mesh:

    y_i = b + sum_{j in N(i)} sum_m A_ijm B_m^T x_j

``mode`` chooses the support (the sampler's ``Level.conv`` / ``pool`` / ``unpool``
neighbourhoods where it defines them, as the connectivity-only sampler of Zhou et al. does;
otherwise the vertices within ``radius`` hops, and the non-zeros of ``Hierarchy.down`` / ``up``):

* ``same``: N(i) = vertices within the kernel radius on the same level (stride 1);
* ``down``: a strided convolution, level l -> l + 1: N(c) = the pool neighbourhood of centre c;
* ``up``: the transposed convolution, level l + 1 -> l: N(i) = the centres whose pool
  neighbourhood contains i.

With ``residual_rate`` r the block adds a residual path (Zhou et al.'s up/down residual layers):
y = sqrt(1 - r) act(conv(x)) + sqrt(r) res(x), the activation on the conv branch only, as the
thesis (l. 1787) and Zhou et al.'s reference (MeshConvolution ``graphAE.py``) compute it; without a
residual path y = act(conv(x)); ``act`` is the ``activation`` module the model supplies (None: the
identity). res averages the input over the same support
with learned non-negative weights normalised to sum to one (|w_ij| / sum_j |w_ij|; the identity
when the vertex count is unchanged) followed by a linear channel map when c_in != c_out.

Evaluation (the same sum in one of three orders, ``order``; ``auto`` takes the cheapest for the
layer's shape and batch by a cost model of multiply-adds plus the floats of the large
intermediates each order materialises (``VCConv.costs``, ``FLOAT_COST``), which is ``sum`` for the
encoder's strided layers and ``basis`` for the decoder's transposed ones at the thesis's sizes):

* ``sum``: T_im = sum_j A_ijm x_j on the output side (one gather of the input rows, one batched
  (M x K) @ (K x b c_in) product per output vertex), then y_i = sum_m B_m^T T_im as one dense
  product; the residual's weighted average rides along as an (M+1)-th coefficient;
* ``basis``: Z_jm = B_m^T x_j on the input side (one dense product), then each input vertex j
  sends sum_m A_ijm Z_jm to the outputs i whose support holds it (one batched
  (K' x M) @ (M x b c_out) product per input vertex, K' = how many supports hold j, and one
  scatter-add). For a transposed layer the inputs are the few coarse vertices, so the basis
  product runs there: about 4x fewer multiply-adds than ``sum`` in the thesis's decoder;
* ``kernel``: the explicit kernels W_ij = sum_m A_ijm B_m first, as in Zhou et al.'s code.

Supports are padded to a fixed size per bucket: vertices are sorted by their support size and cut
into up to four buckets, each padded only to its own largest support (padding is about a third
of the thesis's supports in one bucket). Activations run vertex-major ((n, b, c) in memory) so
gathers and scatters move whole rows and their backward passes are an ``index_add`` and an
``index_select``; the output is returned as a (b, n, c) view of that layout.

On float32 CPU tensors every order runs its per-vertex products in native kernels
(``fwk_vcconv.native``: the exact supports, no padding, no gathered intermediates; 1.3-1.6x a
training step, docs/methods/autoencoders.md "Speed"; ``kernel``: every coefficient row's kernel
from one product, then y_i = G_i W_i per output vertex on its gathered rows), and the products
with the basis, where tall and narrow (``native.tall``: the outer layers' (n b) x c M @ c M x o),
in ``native.tall_product`` (1.1-1.2x the chapter 5 width's step); the ``basis`` order of layers with
at most ``LANES_MAX_IN`` input and ``LANES_MAX_OUT`` output channels runs in one pass with the batch as the vector
(``native.basis_lanes``: the basis product made in cache), and so does the ``kernel`` order of layers
with at most ``KERNEL_LANES_MAX_IN`` input and ``KERNEL_LANES_MAX_OUT`` output channels
(``native.kernel_lanes``), and the ``sum`` order's forward (``native.sum_product``, the kernels as the
vector): together 1.10-1.46x the chapter 5 width's step (``benchmarks/training.py``, "no lanes",
2026-12-07), on CPUs with AVX-512; elsewhere (bf16 autocast,
float64, CUDA, no compiler, ``FWK_VCCONV_NATIVE=0``) the torch code below. ``auto`` prices the
orders for the code that runs (the native kernels skip the padding and the slot-sized
intermediates, but ``kernel`` still copies each slot's input row into its vertex's block), which
moves one layer measured: the chapter 5 width's first encoder layer takes ``kernel`` (20-30 ms
forward and backward against ``sum``'s 25-34; ``benchmarks/vcconv_orders.py``).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn.utils import skip_init

from fwk.errors import RecipeError
from fwk.graph import adjacency, buckets, padded_rows, reach
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS, STRIDED_BUILD_ARGS

from . import native

MODES = ("same", "down", "up")
ORDERS = ("auto", "sum", "basis", "kernel")  # evaluation order of the same sum (see the module docstring)
#: ``auto``'s price of a float of a large intermediate (``VCConv.traffic``), in multiply-adds of a
#: dense product. Measured 2026-12-03 (every order of every layer of the thesis-width and the
#: chapter 5 width VAE, forward and backward, 2 threads, ICT-FaceKit's face-head, batch 16): 6 to
#: 32 pick the fastest order for all 20 layers; 0 (multiply-adds alone) picked ``kernel`` for the
#: chapter 5 decoder's last two layers, 36 and 59 ms against ``basis``'s 22 and 42 ms.
FLOAT_COST = 16


def support(hierarchy, level: int, mode: str, radius: int):
    """(index (n_out, K), mask (n_out, K), n_in, n_out): the padded support of a ``mode``
    convolution at ``level``, the sampler's ``Level.conv`` / ``pool`` / ``unpool`` where it
    defines them, else the vertices within ``radius`` hops (same) or the non-zeros of
    ``Hierarchy.down`` / ``up`` (down / up)."""
    lv = hierarchy.levels[level]
    if mode == "same":
        if lv.conv is not None:
            return lv.conv.index, lv.conv.mask, lv.n_vertices, lv.n_vertices
        R = reach(adjacency(lv.edges, lv.n_vertices), radius)
        idx, mask = padded_rows(R, first=np.arange(lv.n_vertices))
        return idx, mask, lv.n_vertices, lv.n_vertices
    nxt = hierarchy.levels[level + 1]
    if mode == "down":
        if nxt.pool is not None:
            return nxt.pool.index, nxt.pool.mask, lv.n_vertices, nxt.n_vertices
        idx, mask = padded_rows(hierarchy.down[level])
        return idx, mask, lv.n_vertices, nxt.n_vertices
    if lv.unpool is not None:
        return lv.unpool.index, lv.unpool.mask, nxt.n_vertices, lv.n_vertices
    idx, mask = padded_rows(hierarchy.up[level])
    return idx, mask, nxt.n_vertices, lv.n_vertices


def _bucketed(rows: list[np.ndarray], cols: list[np.ndarray], n_rows: int):
    """Pair lists grouped by row, cut into buckets of similar length (``fwk.graph.buckets``).

    rows[r]: the (other vertex, coefficient position) pairs of row r as two equal-length arrays
    in ``cols`` order. Returns (order (n_rows,) rows in bucket order, [(start, count, width)],
    other (sum count*width,), pos (same), valid (same, float)): padded slots repeat the row's
    first pair (or 0) with valid = 0."""
    counts = np.array([len(c) for c in cols], dtype=np.int64)
    order, spans = buckets(counts)
    other, pos, valid = [], [], []
    for start, count, width in spans:
        o = np.zeros((count, width), np.int64)
        p = np.zeros((count, width), np.int64)
        v = np.zeros((count, width), np.float32)
        for r, row in enumerate(order[start:start + count]):
            k = len(cols[row])
            if k:
                o[r, :k], p[r, :k], v[r, :k] = rows[row], cols[row], 1.0
                o[r, k:], p[r, k:] = rows[row][0], cols[row][0]
        other.append(o.ravel())
        pos.append(p.ravel())
        valid.append(v.ravel())
    return order, spans, np.concatenate(other), np.concatenate(pos), np.concatenate(valid)


#: the ``basis`` order runs in lanes (``native.basis_lanes``: the batch as the vector, the basis product
#: made in cache) for layers with at most this many output channels, where MKL's per-vertex products
#: are narrow; wider layers keep the tall product and ``native.basis_product``. 8 until session 28; 16 since
#: (measured with the lanes' bias; the second route to the coefficients' gradient then in the code, since removed,
#: was not taken on these layers): the chapter 5 width's 32 -> 16
#: decoder layer 1.10-1.11x forward and backward in three runs, its 32 -> 32 layer 0.82x and the thesis
#: width's 64 -> 32 0.87x in lanes (2 threads, batch 16, alternating in one process, 2026-12-07)
LANES_MAX_OUT = 16
#: ... and at most this many input channels: with 16 output channels allowed, the thesis width's 128 -> 16 latent
#: layer went to the lanes (auto prices them without Z) and took 5.1 ms against 1.4 ms for ``basis_product`` and
#: 1.7 for ``kernel`` (``benchmarks/vcconv_orders.py``, 2026-12-07); 32 is the widest input measured faster in lanes
#: (the chapter 5 width's 32 -> 16, the thesis width's 32 -> 3)
LANES_MAX_IN = 32
#: the ``kernel`` order runs in lanes (``native.kernel_lanes``) for layers with at most this many input
#: channels and at most ``KERNEL_LANES_MAX_OUT`` output channels (the chapter 5 width's first layer, 3 -> 8:
#: 2.0-2.2x its per-vertex products forward and 1.9-2.0x the input's gradient). Measured 2026-12-07 on the
#: first layer (11,248 -> 3,089 vertices, forward and backward, 2 threads, batch 16) against
#: ``kernel_product``, when the kernels' gradient was still ``kernel_product``'s BLAS call for both (it is
#: ``kernel_lanes``' own now, 3.5x on that layer): 1.10-1.20x for 9 -> 8 (the DR representation's 9
#: features), 1.14-1.19x for 12, 16, 24, 32 and 64 -> 8, 1.03-1.07x for 9 -> 32 and 32 -> 32, 0.97-0.98x
#: for 64 -> 64 (until then 8 -> any)
KERNEL_LANES_MAX_IN = 64
KERNEL_LANES_MAX_OUT = 32


def _vertex_major_gradient(g: torch.Tensor) -> torch.Tensor:
    """The gradient of a conv's vertex-major result y (n, b, c), made contiguous once (a hook on y, which
    the conv hands on as the (b, n, c) view). A gradient that arrives batch-major (the last layer's, from
    the loss) reaches y as a transposed view; without this each native backward that takes it (the
    products, the residual's average, the bias's sum) made its own transposing copy: about 0.9 ms each in
    the chapter 5 width's step, for (11,248, 16, 3) floats."""
    return g.contiguous()


def _fused_elu(act) -> bool:
    """Whether the conv's activation is torch's ELU with alpha 1 (the thesis's, and fwk's models') and the lane
    kernels run here: then ``native.elu_mix`` does the activation and the residual mix in one pass each way
    (1.2 ms of torch's ELU alone in the chapter 5 width's step)."""
    return type(act) is nn.ELU and act.alpha == 1.0 and not act.inplace and native.lanes()


def _dense(A: torch.Tensor, B: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """A @ B (+ bias) on the native kernels' path: ``native.tall_product`` for the tall, narrow
    shapes MKL runs slowly (``native.tall``), torch's product otherwise."""
    if native.tall(A, B):
        return native.tall_product(A, B, bias if bias is not None else A.new_empty(0))
    return A @ B if bias is None else torch.addmm(bias, A, B)


class VCConv(nn.Module):
    r"""Spatially varying kernels from a shared basis (Zhou et al. 2020); strided and transposed modes.

    With N(i) the support of output vertex i (``mode``, see the method below), a basis of M
    kernels B_m (c_in x c_out) and per-vertex coefficients A_ijm:

        y_i = b + sum_{j in N(i)} sum_{m=1}^{M} A_ijm B_m^T x_j

    then y = act(y) (``activation``, None: the identity), and with a residual rate r:
    y = sqrt(1 - r) act(y) + sqrt(r) R(sum_{j in N(i)} w~_ij x_j),
    w~_ij = |w_ij| / sum_j |w_ij| (learned; the identity when ``mode="same"``), R a linear
    channel map (no bias) when c_in != c_out, else the identity.

    Plays the strided / transposed role (``strided = True``, ``fwk.protocols.Conv``).

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy.
        level (int): l; ``same`` works on level l, ``down`` maps l -> l + 1, ``up`` l + 1 -> l.
        weight_num (int): M, kernels in the shared basis (default 35, the thesis's).
        mode (str): ``same``, ``down`` (strided) or ``up`` (transposed).
        radius (int): hops of the support where the sampler defines no neighbourhoods.
        residual_rate (float or None): r in [0, 1]; None: no residual path.
        activation (torch.nn.Module or None): applied to the conv branch before the residual mix;
            supplied by the model like the build arguments (not a recipe key); None: no activation.
        order (str): evaluation order of the same sum: ``auto`` (the cheapest by ``costs``), ``sum``,
            ``basis`` or ``kernel`` (see the module docstring); the numbers agree to rounding.

    Shapes:
        - **input:** (b, n_l, c_in) for ``same`` and ``down``, (b, n_{l+1}, c_in) for ``up``
        - **output:** (b, n_l, c_out) for ``same`` and ``up``, (b, n_{l+1}, c_out) for ``down``
          (a view of a vertex-major tensor: use ``reshape``, not ``view``)

    ``reset_parameters()`` draws B_m ~ N(0, 2 / (c_in K)) and A_ijm ~ N(0, 1 / M) (K the padded
    support size), sets b = 0 and the residual weights w_ij = 1, and draws R as
    ``torch.nn.Linear`` does.

    The coefficients A (``coef``, (pairs, M)) and the residual's weights (``res_w``, (pairs,)) hold
    the supports' valid (i, j) pairs only, in (i, k) order: 60 % of the (n_out, K) padded layout in
    the chapter 5 width's VAE (6.2 M parameters instead of 10.2 M; Adam and every gradient pass
    over the coefficients read less). ``padded`` gives that layout, zero at the padding; the
    checkpoints of earlier versions, which stored it, load (``upgrade``: the weights and, on resume,
    Adam's states).
    """

    name = "vcconv"
    build_args = CONV_BUILD_ARGS + STRIDED_BUILD_ARGS  # the model supplies all of them, not the recipe
    strided = True

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, weight_num: int = 35,
                 mode: str = "same", radius: int = 2, residual_rate: float | None = None, order: str = "auto",
                 activation: nn.Module | None = None):
        super().__init__()
        if mode not in MODES:
            raise RecipeError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if order not in ORDERS:
            raise RecipeError(f"order: expected one of {', '.join(ORDERS)}, got {order!r}")
        if residual_rate is not None and not 0.0 <= residual_rate <= 1.0:
            raise RecipeError(f"residual_rate: expected a number in [0, 1], got {residual_rate}")
        self.order = order
        self.activation = activation  # a module (no parameters: the state_dict is unchanged) or None
        idx, mask, self.n_in, self.n_out = support(hierarchy, level, mode, radius)
        # index and mask stay in the state_dict (as before); the evaluation plans below do not
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.register_buffer("mask", torch.as_tensor(mask, dtype=torch.float32))
        K = idx.shape[1]
        self.K = K
        self.c_in = in_channels
        self.n_slots = int(np.asarray(mask, dtype=bool).sum())
        # allocated here, drawn by reset_parameters() in the order they always were: basis, coef, res_lin.
        # coef and res_w hold the supports' valid (i, j) pairs only, row-major in (i, k) (``padded`` gives the
        # (n_out, K, ...) layout of earlier versions, zero at the padding, which no order ever read)
        self.basis = nn.Parameter(torch.empty(weight_num, in_channels, out_channels))
        self.coef = nn.Parameter(torch.empty(self.n_slots, weight_num))
        self.bias = nn.Parameter(torch.empty(out_channels))
        self.r = residual_rate
        self.res_w = self.res_lin = None
        if residual_rate is not None:
            self.res_w = nn.Parameter(torch.empty(self.n_slots)) if mode != "same" else None
            self.res_lin = skip_init(nn.Linear, in_channels, out_channels, bias=False) if in_channels != out_channels else None
        self._plan(np.asarray(idx, dtype=np.int64), np.asarray(mask, dtype=bool))
        self.reset_parameters()

    def _plan(self, idx: np.ndarray, mask: np.ndarray) -> None:
        """The bucketed supports of both sides (non-persistent buffers, moved by ``.to``)."""
        n_out, K = idx.shape
        flat = np.zeros((n_out, K), np.int64)  # each valid (i, k)'s row of coef and res_w (none at the padding)
        flat[mask] = np.arange(int(mask.sum()))
        self.register_buffer("_row_out", torch.as_tensor(np.nonzero(mask)[0]), persistent=False)  # row -> i
        # output side (sum, kernel): each output vertex's valid neighbours and coefficient positions
        o_rows = [idx[i][mask[i]] for i in range(n_out)]
        o_cols = [flat[i][mask[i]] for i in range(n_out)]
        order, self._out_spans, other, pos, valid = _bucketed(o_rows, o_cols, n_out)
        self.register_buffer("_out_src", torch.as_tensor(other), persistent=False)
        self.register_buffer("_out_pos", torch.as_tensor(pos), persistent=False)
        self.register_buffer("_out_valid", torch.as_tensor(valid), persistent=False)
        inv = np.empty(n_out, np.int64)
        inv[order] = np.arange(n_out)
        self.register_buffer("_out_order", torch.as_tensor(order), persistent=False)
        self.register_buffer("_out_inv", torch.as_tensor(inv), persistent=False)
        # input side (basis): for each input vertex j, the (output vertex, coefficient position) pairs holding it
        i_all, k_all = np.nonzero(mask)
        j_all = idx[i_all, k_all]
        srt = np.argsort(j_all, kind="stable")
        splits = np.searchsorted(j_all[srt], np.arange(self.n_in + 1))
        # one gather and one split for all input vertices (an index per vertex was quadratic: 3.5 s
        # of building the thesis's VAE at 11,248 vertices)
        i_rows = np.split(i_all[srt], splits[1:-1])
        i_cols = np.split(flat[i_all, k_all][srt], splits[1:-1])
        order, self._in_spans, other, pos, valid = _bucketed(i_rows, i_cols, self.n_in)
        self.register_buffer("_in_order", torch.as_tensor(order), persistent=False)
        self.register_buffer("_in_dst", torch.as_tensor(other), persistent=False)
        self.register_buffer("_in_pos", torch.as_tensor(pos), persistent=False)
        self.register_buffer("_in_valid", torch.as_tensor(valid), persistent=False)
        # the exact supports as CSR for the native kernels (``native``): output side in output order,
        # input side in input order (i_all / k_all sorted by j above)
        valid = mask.reshape(-1)
        self.register_buffer("_nat_out_offs", torch.as_tensor(np.concatenate([[0], np.cumsum(mask.sum(1))])),
                             persistent=False)
        self.register_buffer("_nat_out_src", torch.as_tensor(idx.reshape(-1)[valid]), persistent=False)
        self.register_buffer("_nat_out_pos", torch.as_tensor(flat.reshape(-1)[valid]), persistent=False)
        self.register_buffer("_nat_in_offs", torch.as_tensor(splits.astype(np.int64)), persistent=False)
        self.register_buffer("_nat_in_dst", torch.as_tensor(i_all[srt]), persistent=False)
        self.register_buffer("_nat_in_pos", torch.as_tensor(flat[i_all, k_all][srt]), persistent=False)
        self._out_slots = int(sum(c * w for _, c, w in self._out_spans))
        self._in_slots = int(sum(c * w for _, c, w in self._in_spans))

    def reset_parameters(self) -> None:
        """B_m ~ N(0, 2 / (c_in K)), A_ijm ~ N(0, 1 / M), b = 0, w_ij = 1, R as torch.nn.Linear."""
        M = self.basis.shape[0]
        with torch.no_grad():
            self.basis.copy_(torch.randn(self.basis.shape) * math.sqrt(2.0 / (self.c_in * self.K)))
            # drawn for every (i, k) as before (the same draws, the same valid values), the padding's left out
            self.coef.copy_((torch.randn(self.n_out, self.K, M) / math.sqrt(M))[self.mask.bool()])
            self.bias.zero_()
            if self.r is not None and self.res_w is not None:
                self.res_w.fill_(1.0)
        if self.r is not None and self.res_lin is not None:
            self.res_lin.reset_parameters()

    # ---- evaluation orders
    def _slots(self, native_kernels: bool) -> tuple[int, int]:
        """(output-side, input-side) slots the evaluation multiplies: the exact supports on the
        native kernels, the bucket-padded ones on the torch code."""
        if native_kernels:
            return len(self._nat_out_src), len(self._nat_in_dst)
        return self._out_slots, self._in_slots

    def multiply_adds(self, b: int, native_kernels: bool = False) -> dict:
        """Multiply-adds of one forward pass per order for batch size b (on the torch code, or on
        the native kernels, which skip the padded slots; there ``kernel`` makes every coefficient row's kernel)."""
        M, c, o = self.basis.shape
        P_out, P_in = self._slots(native_kernels)
        R = self.coef.shape[0]  # the native kernels make every coefficient row's kernel
        return {"sum": P_out * M * b * c + self.n_out * b * M * c * o,
                "basis": self.n_in * b * c * M * o + P_in * M * b * o,
                "kernel": (R if native_kernels else self._out_slots) * M * c * o + P_out * b * c * o}

    def traffic(self, b: int, native_kernels: bool = False) -> dict:
        """Floats of the large intermediates one forward pass materialises per order for batch
        size b (each is written, read, and has a gradient of its size in the backward):

        * ``sum``: the gathered inputs (slots x b c; not on the native kernels) and T (n_out (M + 1) b c);
        * ``basis``: Z (n_in M b o; not in lanes, ``native.basis_lanes``, where it is made in cache), the
          per-slot products and residual terms sent to the outputs (2 x slots b o; not on the native kernels);
        * ``kernel``: the explicit kernels (slots c o; on the native kernels, every coefficient
          row's, rows c o), the gathered inputs, their copy laid out for the product and the
          residual's weighted copy (3 x slots b c; on the native kernels the one copy of each slot's
          input row into its vertex's block, slots b c);

        and the output (n_out b o) for every order."""
        M, c, o = self.basis.shape
        P_out, P_in = self._out_slots, self._in_slots
        y = self.n_out * b * o
        gathered, sent = (0, 0) if native_kernels else (P_out * b * c, 2 * P_in * b * o)
        # the explicit kernels (every coefficient row's on the native kernels), and the gathered inputs: the
        # native kernels copy each slot's input row once, transposed into the vertex's (b, K c) block
        kernel = (self.coef.shape[0] * c * o + self._slots(True)[0] * b * c if native_kernels
                  else P_out * c * o + 3 * P_out * b * c)
        Z = 0 if native_kernels and self._in_lanes(c, o, M) else self.n_in * M * b * o
        return {"sum": gathered + self.n_out * (M + 1) * b * c + y,
                "basis": Z + sent + y,
                "kernel": kernel + y}

    def costs(self, b: int, native_kernels: bool = False) -> dict:
        """The cost model ``auto`` minimises: multiply-adds + ``FLOAT_COST`` x traffic, per order."""
        macs, floats = self.multiply_adds(b, native_kernels), self.traffic(b, native_kernels)
        return {k: macs[k] + FLOAT_COST * floats[k] for k in macs}

    def chosen_order(self, b: int, native_kernels: bool | None = None) -> str:
        """The order ``forward`` uses for batch size b; ``native_kernels``: whether the native
        kernels run (None: whether they are available)."""
        if self.order != "auto":
            return self.order
        if native_kernels is None:
            native_kernels = native.available()
        cost = self.costs(b, native_kernels)
        return min(cost, key=cost.get)

    @staticmethod
    def _in_lanes(c: int, o: int, M: int) -> bool:
        """Whether the ``basis`` order of this layer (c input and o output channels, M kernels) runs in lanes on the
        native path (``native.basis_lanes``; ``LANES_MAX_IN``, ``LANES_MAX_OUT``)."""
        return c <= LANES_MAX_IN and o <= LANES_MAX_OUT and native.lanes(M)

    def _res_weights(self, nat: bool = False):
        """sqrt(r) w~ (one per coefficient row), w~_ij = |w_ij| / sum_j |w_ij| over the support of
        output vertex i; the residual's factor sqrt(r) rides on its weights. ``nat``: by the native
        kernels' ``residual_weights`` (one pass per output vertex instead of six torch ops)."""
        if nat:
            return native.residual_weights(self.res_w, self._nat_out_offs, self._nat_out_pos, math.sqrt(self.r))
        w = self.res_w.abs()
        total = w.new_zeros(self.n_out).index_add_(0, self._row_out, w)
        return w * (math.sqrt(self.r) / total.clamp_min(1e-12)).index_select(0, self._row_out)

    def padded(self, t: torch.Tensor) -> torch.Tensor:
        """coef (rows, M) or res_w (rows,) in the (n_out, K, ...) layout of the supports, zero at the
        padding (the layout of the parameters before 2026-12-07)."""
        out = t.new_zeros(self.n_out, self.K, *t.shape[1:])
        out[self.mask.bool()] = t
        return out

    def upgrade(self, name: str, t: torch.Tensor) -> torch.Tensor:
        """A saved tensor of ``name`` (``coef``, ``res_w``, or an optimiser state of theirs) in the
        layout of its parameter: the padded (n_out, K, ...) layout of earlier versions loses its
        padding; anything else is returned as it is (and load_state_dict reports a mismatch)."""
        param = getattr(self, name, None)
        if name in ("coef", "res_w") and param is not None and t.shape != param.shape \
                and tuple(t.shape[:2]) == (self.n_out, self.K) and t.shape[2:] == param.shape[1:]:
            return t[self.mask.to(t.device).bool()]
        return t

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in ("coef", "res_w"):  # a checkpoint of an earlier version: the padded layout
            if prefix + name in state_dict:
                state_dict[prefix + name] = self.upgrade(name, state_dict[prefix + name])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _gather_out(self, t):
        """Rows of t (coefficient rows, ...) at the output-side slots, zero at padding: (slots, ...)."""
        g = t.index_select(0, self._out_pos)
        return g * self._out_valid.reshape(-1, *([1] * (g.dim() - 1)))

    def _sum(self, xv, b, c, o, M):
        """Output side, per bucket: T_i = A_i^T X_i (one batched product), then one dense product
        with the basis (and the bias); each bucket's rows are copied to their vertices."""
        has_res = self.r is not None and self.res_w is not None
        A = self._gather_out(self.coef.reshape(-1, M))  # (slots, M)
        if has_res:
            A = torch.cat([A, self._gather_out(self._res_weights())[:, None]], 1)  # residual as an (M+1)-th
        Mx = A.shape[1]
        x2 = xv.reshape(self.n_in, b * c)
        # T_i is computed transposed, (b c) x (M + 1) (X_i^T A_i: a transposed operand costs BLAS
        # nothing), so that its rows (beta, q) are already the dense product's layout [(i, beta), (q, m)]:
        # the basis is laid out to match, (c (M + 1)) x o, with a zero row for the residual's column
        Bm = self.basis.permute(1, 0, 2)
        if has_res:
            Bm = torch.cat([Bm, Bm.new_zeros(c, 1, o)], 1)
        Bm = Bm.reshape(c * Mx, o)
        sizes = [count * width for _, count, width in self._out_spans]
        # a gather per bucket (its backward: an index_add into the small input) and a split of the small A
        # (its backward: one cat); slices of large tensors would cost a zero-filled copy each in the backward
        y = res = None
        at = 0
        for (start, count, width), Ab in zip(self._out_spans, A.split(sizes)):
            Xb = x2.index_select(0, self._out_src[at:at + count * width]).reshape(count, width, b * c)
            T = torch.bmm(Xb.transpose(1, 2), Ab.reshape(count, width, Mx))  # (count, b c, M + 1)
            yb = torch.addmm(self.bias, T.reshape(count * b, c * Mx), Bm)
            rows = self._out_order[start:start + count]
            y = yb.new_empty(self.n_out, b, o) if y is None else y  # every row is written by one bucket
            y.index_copy_(0, rows, yb.reshape(count, b, o))
            if has_res:
                res = T.new_empty(self.n_out, b, c) if res is None else res
                res.index_copy_(0, rows, T.reshape(count, b, c, Mx)[..., M])
            at += count * width
        if has_res and self.res_lin is not None:
            res = res @ self.res_lin.weight.t()
        return y, res

    def _residual_map_first(self, c: int, o: int) -> bool:
        """``basis`` order: apply the residual's channel map R to the input rows before the scatter
        (True) or to the scattered average after it, whichever multiplies less."""
        return self.res_lin is not None and self.n_in * c * o + self._in_slots * o \
            <= self._in_slots * c + self.n_out * c * o

    def _sum_native(self, xv, b, c, o, M):
        """``sum`` with the native kernel (``native.sum_product``): T_i and the residual's average
        r_i per output vertex on its exact support (the coefficients and the residual's weights
        read in place), then the same dense product with the basis."""
        has_res = self.r is not None and self.res_w is not None
        w = self._res_weights(True) if has_res else self.coef.new_empty(0)  # (rows,): read in place, as coef
        x2 = xv.reshape(self.n_in, b * c)
        T, r = native.sum_product(x2, self.coef.reshape(-1, M), w, self._nat_out_offs, self._nat_out_src,
                                  self._nat_out_pos)  # (n_out, b c, M), (n_out, b c)
        Bm = self.basis.permute(1, 0, 2).reshape(c * M, o)  # rows (p, m): T's rows (i, beta) are [(i, b), (p, m)]
        y = _dense(T.reshape(self.n_out * b, c * M), Bm, self.bias).reshape(self.n_out, b, o)
        return y, (self._mapped_residual(r, b, c) if has_res else None)

    def _basis_native(self, xv, b, c, o, M):
        """``basis`` with the native kernel (``native.basis_product``): Z_j from one dense product,
        then each input vertex's (K' x M) @ (M x b o) product accumulated at its outputs; the
        residual's weighted average by ``native.weighted_rows``, on the output side."""
        has_res = self.r is not None and self.res_w is not None
        res_first = has_res and self._residual_map_first(c, o)
        d = o if res_first else c
        x2 = xv.reshape(self.n_in, b * c)
        if self._in_lanes(c, o, M):  # the basis product and the slots' products in one pass, the bias as it leaves
            y = native.basis_lanes(xv, self.basis, self.coef.reshape(-1, M), self._nat_in_offs, self._nat_in_dst,
                                   self._nat_in_pos, self.n_out, self.bias)
        else:
            Bm = self.basis.permute(1, 2, 0).reshape(c, o * M)
            Z = _dense(x2.reshape(self.n_in * b, c), Bm).reshape(self.n_in, b * o, M)  # Z_j^T: rows (b, q), columns m
            y = native.basis_product(Z, self.coef.reshape(-1, M), self._nat_in_offs, self._nat_in_dst,
                                     self._nat_in_pos, self.n_out).reshape(self.n_out, b, o) + self.bias
        res = None
        if has_res:
            src = _dense(x2.reshape(self.n_in * b, c), self.res_lin.weight.t()) if res_first else x2  # R x_j
            res = native.weighted_rows(src.reshape(self.n_in, b * d), self._res_weights(True), self._nat_out_offs,
                                       self._nat_out_src, self._nat_out_pos, self._nat_in_offs, self._nat_in_dst,
                                       self._nat_in_pos).reshape(self.n_out, b, d)
            if not res_first and self.res_lin is not None:
                res = self._mapped_residual(res, b, c)
        return y, res

    def _basis(self, xv, b, c, o, M):
        """Input side, per bucket of input vertices: Z_j = x_j [B_1 .. B_M] (one dense product),
        then (K' x M) @ (M x b o) per input vertex and a scatter-add to the outputs (which start
        at the bias)."""
        has_res = self.r is not None and self.res_w is not None
        res_first = has_res and self._residual_map_first(c, o)
        d = o if res_first else c
        x2 = xv.reshape(self.n_in, b * c)
        # Z_j is computed transposed, (b o) x M, straight from one dense product ([q, (p, m)] basis);
        # the per-vertex product takes it as a transposed operand (free in BLAS) instead of a copy
        Bm = self.basis.permute(1, 2, 0).reshape(c, o * M)
        A = self.coef.reshape(-1, M).index_select(0, self._in_pos) * self._in_valid[:, None]  # (slots, M)
        sizes = [count * width for _, count, width in self._in_spans]
        w = (self._res_weights().index_select(0, self._in_pos) * self._in_valid).split(sizes) if has_res \
            else [None] * len(sizes)
        y = res = None  # accumulators in the products' dtype (bf16 under CPU autocast)
        at = 0
        for (start, count, width), Ab, wb in zip(self._in_spans, A.split(sizes), w):
            xb = x2.index_select(0, self._in_order[start:start + count])  # (count, b c)
            Z = (xb.reshape(count * b, c) @ Bm).reshape(count, b * o, M)  # Z_j^T
            Y = torch.bmm(Ab.reshape(count, width, M), Z.transpose(1, 2))  # (count, width, b o)
            dst = self._in_dst[at:at + count * width]
            if y is None:
                y = self.bias.to(Y.dtype).expand(self.n_out, b, o).reshape(self.n_out, b * o).clone()
            y.index_add_(0, dst, Y.reshape(count * width, b * o))
            if has_res:
                src = xb.reshape(count * b, c) @ self.res_lin.weight.t() if res_first else xb  # R x_j
                R = (wb.reshape(count, width, 1) * src.reshape(count, 1, b * d)).reshape(count * width, b * d)
                res = R.new_zeros(self.n_out, b * d) if res is None else res
                res.index_add_(0, dst, R)
            at += count * width
        y = y.reshape(self.n_out, b, o)
        if has_res:
            res = res.reshape(self.n_out, b, d)
            if not res_first and self.res_lin is not None:
                res = res @ self.res_lin.weight.t()
        return y, res

    def _kernel_native(self, xv, b, c, o, M):
        """``kernel`` with the native kernels: every coefficient row's kernel W = A B from one tall
        product (``_dense``), then per output vertex y_i = G_i W_i on its exact support
        (``native.kernel_product``: the rows gathered in cache, one BLAS call), the residual's
        weighted average in the same pass."""
        has_res = self.r is not None and self.res_w is not None
        w = self._res_weights(True) if has_res else self.coef.new_empty(0)
        Wk = _dense(self.coef.reshape(-1, M), self.basis.reshape(M, c * o))  # (rows, c o)
        if c <= KERNEL_LANES_MAX_IN and o <= KERNEL_LANES_MAX_OUT and native.lanes():  # 16 batch entries a register
            # xv made contiguous here, once: the op saves its input for the backward, which would copy it again
            y, r = native.kernel_lanes(xv.contiguous(), Wk, w, self._nat_out_offs, self._nat_out_src, self._nat_out_pos,
                                       o, self.bias)
            return y, (self._mapped_residual(r, b, c) if has_res else None)
        y, r = native.kernel_product(xv.reshape(self.n_in, b * c), Wk, w, self._nat_out_offs, self._nat_out_src,
                                     self._nat_out_pos, b, c, o)
        return y + self.bias, (self._mapped_residual(r, b, c) if has_res else None)

    def _mapped_residual(self, r, b, c):
        """The native kernels' residual average r (n_out, b c) as (n_out, b, c_out): R applied when c != c_out."""
        if self.res_lin is None:
            return r.reshape(self.n_out, b, c)
        return _dense(r.reshape(self.n_out * b, c), self.res_lin.weight.t()).reshape(self.n_out, b, -1)

    def _kernel(self, xv, b, c, o, M):
        """Explicit kernels W_ij = sum_m A_ijm B_m, then y_i = sum_j W_ij^T x_j per output vertex."""
        has_res = self.r is not None and self.res_w is not None
        A = self._gather_out(self.coef.reshape(-1, M))  # (slots, M)
        W = A @ self.basis.reshape(M, c * o)  # (slots, c o)
        X = xv.reshape(self.n_in, b * c).index_select(0, self._out_src)  # (slots, b c)
        sizes = [count * width for _, count, width in self._out_spans]
        w = self._gather_out(self._res_weights()).split(sizes) if has_res else [None] * len(sizes)
        ys, rs = [], []
        for (_, count, width), Xb, Wb, wb in zip(self._out_spans, X.split(sizes), W.split(sizes), w):
            Xb = Xb.reshape(count, width, b, c)
            ys.append(torch.bmm(Xb.transpose(1, 2).reshape(count, b, width * c), Wb.reshape(count, width * c, o)))
            if has_res:
                rs.append((Xb * wb.reshape(count, width, 1, 1)).sum(1))
        y = torch.cat(ys, 0).index_select(0, self._out_inv) + self.bias
        res = None
        if has_res:
            res = torch.cat(rs, 0).index_select(0, self._out_inv)
            if self.res_lin is not None:
                res = res @ self.res_lin.weight.t()
        return y, res

    def forward(self, x):
        b, _, c = x.shape
        M, _, o = self.basis.shape
        xv = x.transpose(0, 1)  # vertex-major (n_in, b, c); free when x is the previous layer's output
        usable = native.usable(x, self.coef)
        order = self.chosen_order(b, usable)
        nat = usable
        evaluate = {"sum": self._sum_native if nat else self._sum, "basis": self._basis_native if nat else self._basis,
                    "kernel": self._kernel_native if nat else self._kernel}[order]
        y, res = evaluate(xv, b, c, o, M)  # y includes the bias; res (strided modes) includes sqrt(r)
        if self.r is not None and res is None:  # mode same: the identity (or R) on the input itself
            res = math.sqrt(self.r) * (xv if self.res_lin is None else xv @ self.res_lin.weight.t())
        last = nat and self.activation is None and self.r is not None and native.lanes()
        if nat and (_fused_elu(self.activation) or last):  # the activation and the mix in one pass (native.elu_mix)
            # a last layer's result (no activation) laid out batch-major: its transposed view, handed on, is
            # contiguous, as the decoder's result and the loss want it (fwk_autoencoder's batch_major)
            y = native.elu_mix(y, res if self.r is not None else y.new_empty(0),
                               math.sqrt(1 - self.r) if self.r is not None else 1.0, not last, last)
        else:
            if self.activation is not None:
                y = self.activation(y)
            if self.r is not None:
                y = torch.add(res, y, alpha=math.sqrt(1 - self.r))
        if usable and y.requires_grad and not last:  # elu_mix's backward reads a batch-major gradient itself
            y.register_hook(_vertex_major_gradient)
        return y.transpose(0, 1)


@hookimpl
def fwk_register_convs():
    return [VCConv]
