"""Conv ``vcconv``: the spatially varying convolution of the fully convolutional mesh
autoencoder (Zhou et al. 2020, "Fully Convolutional Mesh Autoencoder using Efficient Spatially
Varying Kernels"; thesis 3.3, 3.4, appendix A).

A global basis of M kernels B_m (c_in x c_out, ``weight_num`` = M, thesis: 35) is shared by the
whole mesh; each output vertex i has its own sampling coefficients A_ijm for every vertex j of
its neighbourhood N(i), so the kernel W_ij = sum_m A_ijm B_m varies over the mesh:

    y_i = b + sum_{j in N(i)} sum_m A_ijm B_m^T x_j
        = b + sum_m B_m^T (sum_j A_ijm x_j)            (computed in this cheaper order)

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
Neighbourhoods are padded to a fixed size with a mask; everything is one gather and two matrix
products, in whichever of two orders needs fewer multiply-adds for the layer's shape and batch
(sum over the neighbourhood first, or the explicit kernels W_ij first as in Zhou et al.'s code).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn.utils import skip_init

from fwk.errors import RecipeError
from fwk.graph import adjacency, padded_rows, reach
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS

MODES = ("same", "down", "up")
ORDERS = ("auto", "sum", "kernel")  # evaluation order of the same sum (see forward); auto: fewer multiply-adds


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
        order (str): evaluation order of the same sum: ``auto`` (fewer multiply-adds), ``sum``
            or ``kernel`` (see ``forward``); the numbers agree to rounding.

    Shapes:
        - **input:** (b, n_l, c_in) for ``same`` and ``down``, (b, n_{l+1}, c_in) for ``up``
        - **output:** (b, n_l, c_out) for ``same`` and ``up``, (b, n_{l+1}, c_out) for ``down``

    ``reset_parameters()`` draws B_m ~ N(0, 2 / (c_in K)) and A_ijm ~ N(0, 1 / M) (K the padded
    support size), sets b = 0 and the residual weights w_ij = 1, and draws R as
    ``torch.nn.Linear`` does.
    """

    name = "vcconv"
    build_args = CONV_BUILD_ARGS
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
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.register_buffer("mask", torch.as_tensor(mask, dtype=torch.float32))
        K = idx.shape[1]
        self.K = K
        self.c_in = in_channels
        # allocated here, drawn by reset_parameters() in the order they always were: basis, coef, res_lin
        self.basis = nn.Parameter(torch.empty(weight_num, in_channels, out_channels))
        self.coef = nn.Parameter(torch.empty(self.n_out, K, weight_num))
        self.bias = nn.Parameter(torch.empty(out_channels))
        self.r = residual_rate
        if residual_rate is not None:
            self.res_w = nn.Parameter(torch.empty(self.n_out, K)) if mode != "same" else None
            self.res_lin = skip_init(nn.Linear, in_channels, out_channels, bias=False) if in_channels != out_channels else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """B_m ~ N(0, 2 / (c_in K)), A_ijm ~ N(0, 1 / M), b = 0, w_ij = 1, R as torch.nn.Linear."""
        M = self.basis.shape[0]
        with torch.no_grad():
            self.basis.copy_(torch.randn(self.basis.shape) * math.sqrt(2.0 / (self.c_in * self.K)))
            self.coef.copy_(torch.randn(self.coef.shape) / math.sqrt(M))
            self.bias.zero_()
            if self.r is not None and self.res_w is not None:
                self.res_w.fill_(1.0)
        if self.r is not None and self.res_lin is not None:
            self.res_lin.reset_parameters()

    def forward(self, x):
        b, _, c = x.shape
        n, K, M = self.n_out, self.K, self.coef.shape[2]
        c_out = self.basis.shape[2]
        A = self.coef * self.mask[:, :, None]
        # two orders of the same sum, chosen by their multiply-add count for this batch size:
        #   (a) T_im = sum_j A_ijm x_j, then y_i = sum_m B_m^T T_im:  n M b c (K + c_out)
        #   (b) W_ij = sum_m A_ijm B_m (explicit kernels), then y_i = sum_j W_ij^T x_j:  n K c c_out (M + b)
        # (b) wins where c_out is small next to K and b (the decoder's last, finest levels): it
        # also never builds the (n, M, b, c) intermediate, 800 MB at 11k vertices with c = 32
        explicit = self.order == "kernel" or (self.order == "auto" and K * c_out * (M + b) < M * b * (K + c_out))
        # vertex-major gather (n, K, b, c); padded neighbours get zero coefficients
        X = x.transpose(0, 1)[self.index.reshape(-1)].reshape(n, K, b, c)
        if explicit:
            # one batched (b x K c) @ (K c x c_out) product per vertex
            W = (A.reshape(n * K, M) @ self.basis.reshape(M, c * c_out)).reshape(n, K * c, c_out)
            y = torch.bmm(X.transpose(1, 2).reshape(n, b, K * c), W).transpose(0, 1) + self.bias
        else:
            # one batched (M x K) @ (K x b c) product per output vertex, then one (b n, M c) @ (M c, c_out)
            T = torch.bmm(A.transpose(1, 2), X.reshape(n, K, b * c))
            T = T.reshape(n, M, b, c).permute(2, 0, 1, 3).reshape(b * n, M * c)
            y = (T @ self.basis.reshape(M * c, -1)).reshape(b, n, -1) + self.bias
        if self.activation is not None:
            y = self.activation(y)
        if self.r is None:
            return y
        if self.res_w is None:
            res = x
        else:
            w = self.res_w.abs() * self.mask
            w = w / w.sum(1, keepdim=True).clamp_min(1e-12)
            res = torch.einsum("nk,nkbc->bnc", w, X)
        if self.res_lin is not None:
            res = self.res_lin(res)
        return math.sqrt(1 - self.r) * y + math.sqrt(self.r) * res


@hookimpl
def fwk_register_convs():
    return [VCConv]
