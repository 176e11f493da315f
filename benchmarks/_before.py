"""A frozen copy of the conv implementations (vcconv, spiral++) and of the networks that used
them (fwk_autoencoder's Encoder / Decoder and LatentConvEncoder / LatentConvDecoder, fwk.graph's
sparse_apply) as of commit 5b25de3, before the training-throughput work of issue 17, so that
``benchmarks/training.py`` can time today's code against them side by side in one process.

Copied verbatim except: the classes are built directly (no registry, no Spec), spiral++'s
spirals come from ``fwk.graph.spirals`` without the memo, and the networks take the model's
hierarchy. Not used by fwk itself; only the timing benchmark imports it.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn.utils import skip_init

from fwk.errors import RecipeError
from fwk.graph import adjacency, padded_rows, reach, spirals, torch_sparse
from fwk.protocols import CONV_BUILD_ARGS

MODES = ("same", "down", "up")
ORDERS = ("auto", "sum", "kernel")


def sparse_apply(M, x):
    """(m, n) sparse torch matrix applied to every sample of x (b, n, c) -> (b, m, c)."""
    b, n, c = x.shape
    y = torch.sparse.mm(M, x.transpose(0, 1).reshape(n, b * c))
    return y.reshape(M.shape[0], b, c).transpose(0, 1)


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


class VCConv(nn.Module):  # frozen: fwk_vcconv as of 5b25de3
    r"""Spatially varying kernels from a shared basis (Zhou et al. 2020); strided and transposed modes.

    With N(i) the support of output vertex i (``mode``, see the method below), a basis of M
    kernels B_m (c_in x c_out) and per-vertex coefficients A_ijm:

        y_i = b + sum_{j in N(i)} sum_{m=1}^{M} A_ijm B_m^T x_j

    and with a residual rate r: y = sqrt(1 - r) y + sqrt(r) R(sum_{j in N(i)} w~_ij x_j),
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
                 mode: str = "same", radius: int = 2, residual_rate: float | None = None, order: str = "auto"):
        super().__init__()
        if mode not in MODES:
            raise RecipeError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if order not in ORDERS:
            raise RecipeError(f"order: expected one of {', '.join(ORDERS)}, got {order!r}")
        if residual_rate is not None and not 0.0 <= residual_rate <= 1.0:
            raise RecipeError(f"residual_rate: expected a number in [0, 1], got {residual_rate}")
        self.order = order
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


class SpiralPP(nn.Module):  # frozen: fwk_spiralpp as of 5b25de3
    r"""SpiralNet++ convolution (fixed-length spirals, shared linear layer).

    With S(i) = (s_1 = i, s_2, ..., s_L) the spiral of vertex i on the level's mesh (see the
    method below):

        x'_i = W [x_{s_1} || x_{s_2} || ... || x_{s_L}] + b,    W in R^{c_out x L c_in}, b in R^{c_out}

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy; the level must be a
            triangle mesh (``Level.faces``).
        level (int): the level the convolution works on (stride 1).
        length (int): L, entries per spiral (default 9).
        dilation (int): keep every d-th entry of a spiral L d long (default 1).

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` draws W Xavier-uniform and sets b = 0 (the constructor's
    ``torch.nn.Linear`` draws its own initialisation first, so the random stream is that of the
    reference implementation).
    """

    name = "spiral++"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, length: int = 9,
                 dilation: int = 1):
        super().__init__()
        idx = spirals(hierarchy.levels[level].faces, hierarchy.levels[level].n_vertices, length, dilation)
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.length = length
        self.layer = nn.Linear(in_channels * length, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """W Xavier-uniform, b = 0."""
        nn.init.xavier_uniform_(self.layer.weight)
        nn.init.zeros_(self.layer.bias)

    def forward(self, x):
        b, n, c = x.shape
        g = x[:, self.index.reshape(-1)].reshape(b, n, self.length * c)
        return self.layer(g)


# ---------------------------------------------------------------- the networks (fwk_autoencoder, 5b25de3)

class _Sparse(nn.Module):
    """A fixed sparse operator (kept as a buffer so ``.to(device)`` moves it)."""

    def __init__(self, M):
        super().__init__()
        self.register_buffer("M", torch_sparse(M))

    def forward(self, x):
        return sparse_apply(self.M, x)


class Encoder(nn.Module):
    """Conv, activation and pooling per level, then a linear map to the latent (mu, logvar or None)."""

    def __init__(self, conv, hierarchy, channels, latent, variational, act):
        super().__init__()
        L = len(channels) - 1
        self.convs = nn.ModuleList(conv(channels[i], channels[i + 1], hierarchy, i) for i in range(L))
        self.pools = nn.ModuleList(_Sparse(hierarchy.down[i]) for i in range(L))
        self.act = act()
        d = hierarchy.levels[L].n_vertices * channels[-1]
        self.mu = nn.Linear(d, latent)
        self.logvar = nn.Linear(d, latent) if variational else None

    def forward(self, x):
        for conv, pool in zip(self.convs, self.pools):
            x = pool(self.act(conv(x)))
        h = x.flatten(1)
        return self.mu(h), (self.logvar(h) if self.logvar is not None else None)


class Decoder(nn.Module):
    """A linear map from the latent, then unpooling, conv and activation per level, and an output conv."""

    def __init__(self, conv, hierarchy, channels, latent_in, out_channels, act):
        super().__init__()
        L = len(channels) - 1
        self.n_last, self.c_last = hierarchy.levels[L].n_vertices, channels[-1]
        self.fc = nn.Linear(latent_in, self.n_last * self.c_last)
        self.unpools = nn.ModuleList(_Sparse(hierarchy.up[i]) for i in reversed(range(L)))
        self.convs = nn.ModuleList(conv(channels[min(i + 2, L)], channels[i + 1], hierarchy, i)
                                   for i in reversed(range(L)))
        self.out = conv(channels[1], out_channels, hierarchy, 0)
        self.act = act()

    def forward(self, z):
        x = self.fc(z).reshape(len(z), self.n_last, self.c_last)
        for unpool, conv in zip(self.unpools, self.convs):
            x = self.act(conv(unpool(x)))
        return self.out(x)


class LatentConvEncoder(nn.Module):
    """Strided convolutions down to the latent level; z = the flattened (n_latent, c_L) map."""

    def __init__(self, conv, hierarchy, channels, variational, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        self.c_last, self.variational = channels[-1], variational
        outs = [*channels[1:-1], channels[-1] * (2 if variational else 1)]
        self.convs = nn.ModuleList(conv(channels[i], outs[i], hierarchy, i, mode="down", residual_rate=residual_rate)
                                   for i in range(L))
        self.act = act()

    def forward(self, x):
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < len(self.convs) - 1:
                x = self.act(x)
        mu = x[..., :self.c_last].flatten(1)
        return mu, (x[..., self.c_last:].flatten(1) if self.variational else None)


class LatentConvDecoder(nn.Module):
    """Transposed convolutions from the latent level (a linear layer first only for foreign codes)."""

    def __init__(self, conv, hierarchy, channels, latent_in, out_channels, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        self.n_last, self.c_last = hierarchy.levels[L].n_vertices, channels[-1]
        d = self.n_last * self.c_last
        self.fc = nn.Linear(latent_in, d) if latent_in != d else None
        chans = [out_channels, *channels[1:]]
        self.convs = nn.ModuleList(conv(chans[i + 1], chans[i], hierarchy, i, mode="up", residual_rate=residual_rate)
                                   for i in reversed(range(L)))
        self.act = act()

    def forward(self, z):
        x = (self.fc(z) if self.fc is not None else z).reshape(len(z), self.n_last, self.c_last)
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < len(self.convs) - 1:
                x = self.act(x)
        return x


def vcconv_vae(hierarchy, in_channels, channels, weight_num=35, residual_rate=0.5):
    """Today's fully convolutional vcconv VAE on ``hierarchy`` (with its latent level)."""
    conv = lambda *a, **k: VCConv(*a, weight_num=weight_num, **k)  # noqa: E731
    L = len(channels)
    ch = [in_channels, *channels][:L + 1]
    enc = LatentConvEncoder(conv, hierarchy, ch, True, nn.ELU, residual_rate)
    dec = LatentConvDecoder(conv, hierarchy, ch, hierarchy.levels[L].n_vertices * ch[-1], in_channels, nn.ELU,
                            residual_rate)
    return enc, dec


def spiralpp_ae(hierarchy, in_channels, channels, latent, length=9):
    """Today's spiral++ AE (pooled encoder / decoder) on ``hierarchy``."""
    conv = lambda *a: SpiralPP(*a, length=length)  # noqa: E731
    ch = [in_channels, *channels][:len(hierarchy.levels)]
    return (Encoder(conv, hierarchy, ch, latent, False, nn.ELU),
            Decoder(conv, hierarchy, ch, latent, in_channels, nn.ELU))
