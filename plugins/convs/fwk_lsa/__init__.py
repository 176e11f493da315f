"""Conv ``lsa``: LSA-3DMM (Gao et al. 2021, "Learning Local Neighboring Structure for Robust 3D
Shape Representation", AAAI; the PaiConv operator; thesis 3.3).

Each vertex i has an ordered neighbourhood N(i) of K entries: the vertex, then its first K - 1
adjacency entries in index order (K = 9: the vertex + 8), padded with i itself where it has
fewer (the reference pads with a zero dummy vertex; with a free A_i the two are equally
expressive: A_i can zero the padded rows). A per-vertex learned K x K matrix A_i, shared
across samples and initialised to the identity, re-weights the neighbourhood, then one shared
linear layer maps it:

    X_i = [x_j]_{j in N(i)}  (K x c),   x~_i = A_i^T X_i,   x'_i = W vec(x~_i) + b.

At initialisation the layer is exactly a plain neighbourhood linear layer. Computed as one
gather, one batched (n; K x K) @ (K x b c) product and one matrix product.

``basis: B`` selects the "tiny" variant (PaiConvSmall of the reference code): A_i =
sum_m w_im B_m mixes B shared K x K bases (each initialised to the identity) with weights
w_i = softmax(MLP(phi_i) / tau_i), where phi_i are random Fourier features (64 frequencies,
sin and cos) of the template's neighbourhood geometry (x_j - x_i, x_i, |x_j - x_i| for j in
N(i), positions scaled to the level's unit radius) and tau_i = 0.01 + 0.09 sigmoid(t^T phi_i) a
learned per-vertex temperature. The reference uses B = 32 and a free A_i on small levels: levels
with at most ``basis_min_vertices`` vertices keep a free A_i here too. Not reproduced: the
reference's ELU between the re-weighting and the linear layer (the model's activation follows
the conv instead).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn.utils import skip_init

from fwk.errors import RecipeError
from fwk.graph import neighbourhoods
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


def fourier_features(V: np.ndarray, idx: np.ndarray, n_freq: int = 64, generator=None) -> torch.Tensor:
    """(n, 2 n_freq) sin/cos features of each vertex's neighbourhood geometry (see the docstring)."""
    V = np.asarray(V, dtype=np.float64)
    V = V - V.mean(0)
    V = V / max(float(np.linalg.norm(V, axis=1).max()), 1e-12)
    rel = V[idx] - V[:, None, :]                                          # (n, K, 3)
    g = np.concatenate([rel, np.broadcast_to(V[:, None, :], rel.shape), np.linalg.norm(rel, axis=2, keepdims=True)], 2)
    g = torch.as_tensor(g.reshape(len(V), -1), dtype=torch.float32)       # (n, 7K)
    B = torch.randn(g.shape[1], n_freq, generator=generator)
    p = 2 * math.pi * g @ B
    return torch.cat([torch.sin(p), torch.cos(p)], 1)


class LSA(nn.Module):
    r"""LSA-3DMM local structure-aware adaptive convolution (per-vertex K x K weighting).

    With N(i) = (i, j_2, ..., j_K) vertex i's ordered neighbourhood and X_i = [x_j]_{j in N(i)}
    (K x c_in):

        x'_i = W vec(A_i^T X_i) + b,    A_i in R^{K x K} (per vertex), W in R^{c_out x K c_in}

    A_i is a free parameter initialised to the identity, or with ``basis`` B (the "tiny"
    variant) A_i = sum_m w_im B_m, w_i = softmax(MLP(phi_i) / tau_i) (see the method below).

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy (any sampler: the level's
            ``edges``, and its ``vertices`` for the tiny variant's features where present).
        level (int): the level the convolution works on (stride 1).
        k (int): K, the neighbourhood size: the vertex and its first K - 1 neighbours (default 9).
        basis (int or None): B shared basis matrices (the tiny variant); None: a free A_i.
        basis_min_vertices (int): levels with at most this many vertices keep a free A_i.

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` sets every A_i (or every B_m) to the identity, draws the linear
    layers as ``torch.nn.Linear`` does and the tiny variant's free features (levels without
    positions) ~ N(0, 0.01^2); the random Fourier frequencies are a fixed buffer, drawn once.
    """

    name = "lsa"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, k: int = 9,
                 basis: int | None = None, basis_min_vertices: int = 128):
        super().__init__()
        if k < 1:
            raise RecipeError(f"k: the neighbourhood size must be at least 1, got {k}")
        if basis is not None and basis < 1:
            raise RecipeError(f"basis: at least 1 shared basis matrix (or null for a free matrix per vertex), got {basis}")
        lv = hierarchy.levels[level]
        n = lv.n_vertices
        idx = neighbourhoods(np.asarray(lv.edges, dtype=np.int64).reshape(-1, 2), n, k)
        self.register_buffer("index", torch.as_tensor(idx.reshape(-1), dtype=torch.long))
        self.k, self.n = k, n
        self.tiny = bool(basis) and n > basis_min_vertices
        # the layers are allocated without initialising (skip_init); reset_parameters() draws
        # them in the order they were always drawn: mix, temp, phi_free, layer
        if self.tiny:
            if lv.vertices is not None:
                phi = fourier_features(lv.vertices, idx)
            else:  # no positions on this level: learned per-vertex features instead
                phi = torch.zeros(n, 128)
            self.register_buffer("phi", phi)
            self.mix = skip_init(nn.Linear, phi.shape[1], basis)
            self.temp = skip_init(nn.Linear, phi.shape[1], 1)
            self.bases = nn.Parameter(torch.empty(basis, k, k))
            self.phi_free = nn.Parameter(torch.empty(n, phi.shape[1])) if lv.vertices is None else None
            self.A = None
        else:
            self.A = nn.Parameter(torch.empty(n, k, k))
        self.layer = skip_init(nn.Linear, in_channels * k, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """A_i (or B_m) = I; the linear layers as torch.nn.Linear; free features ~ N(0, 0.01^2)."""
        with torch.no_grad():
            if self.tiny:
                self.mix.reset_parameters()
                self.temp.reset_parameters()
                self.bases.copy_(torch.eye(self.k).repeat(self.bases.shape[0], 1, 1))
                if self.phi_free is not None:
                    self.phi_free.copy_(0.01 * torch.randn(self.phi_free.shape))
            else:
                self.A.copy_(torch.eye(self.k).repeat(self.n, 1, 1))
        self.layer.reset_parameters()

    def weights(self) -> torch.Tensor:
        """(n, K, K) the per-vertex matrices A_i."""
        if self.A is not None:
            return self.A
        phi = self.phi + self.phi_free if self.phi_free is not None else self.phi
        tau = torch.sigmoid(self.temp(phi)) * (0.1 - 0.01) + 0.01
        w = torch.softmax(self.mix(phi) / tau, dim=1)
        return torch.einsum("nm,mij->nij", w, self.bases)

    def forward(self, x):
        b, n, c = x.shape
        K = self.k
        xt = x.transpose(0, 1).reshape(n, b * c)                           # (n, b c)
        X = xt[self.index].reshape(n, K, b * c)                            # X_i, the batch side by side
        Xt = torch.bmm(self.weights().transpose(1, 2), X)                  # A_i^T X_i
        Xt = Xt.reshape(n, K, b, c).transpose(1, 2).reshape(n, b, K * c)
        return self.layer(Xt).transpose(0, 1)


@hookimpl
def fwk_register_convs():
    return [LSA]
