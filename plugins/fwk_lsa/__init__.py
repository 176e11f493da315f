"""Conv ``lsa``: LSA-3DMM (Gao et al. 2021, "Learning Local Structure-Aware Adaptive
Convolutions", PaiConv; thesis 3.3).

Each vertex i has an ordered neighbourhood N(i) of K entries: the vertex and its first K - 1
adjacency entries (padded with i). A per-vertex learned K x K matrix A_i, shared across samples
and initialised to the identity, re-weights the neighbourhood, then one shared linear layer maps
it:  X_i = [x_j]_{j in N(i)} (K x c),  x~_i = A_i^T X_i,  x'_i = W vec(x~_i) + b.
With ``basis: B`` (the "tiny" variant) A_i = sum_m softmax(alpha_i)_m B_m mixes B shared K x K
bases with per-vertex weights instead of one free matrix per vertex.
"""
from __future__ import annotations

import torch
from torch import nn

from fwk.graph import neighbourhoods
from fwk.hookspecs import hookimpl


class LSA(nn.Module):
    """LSA-3DMM local structure-aware adaptive convolution (per-vertex K x K weighting)."""

    name = "lsa"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, k: int = 9,
                 basis: int | None = None):
        super().__init__()
        lv = hierarchy.levels[level]
        idx = neighbourhoods(lv.edges, lv.n_vertices, k)
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.k = k
        n = lv.n_vertices
        if basis:
            self.bases = nn.Parameter(torch.eye(k).repeat(basis, 1, 1) + 0.01 * torch.randn(basis, k, k))
            self.alpha = nn.Parameter(torch.zeros(n, basis))
            self.A = None
        else:
            self.A = nn.Parameter(torch.eye(k).repeat(n, 1, 1))
        self.layer = nn.Linear(in_channels * k, out_channels)

    def weights(self):
        if self.A is not None:
            return self.A
        return torch.einsum("nm,mij->nij", torch.softmax(self.alpha, dim=1), self.bases)

    def forward(self, x):
        b, n, c = x.shape
        X = x[:, self.index.reshape(-1)].reshape(b, n, self.k, c)
        Xt = torch.einsum("nkj,bnkc->bnjc", self.weights(), X)  # A_i^T X_i
        return self.layer(Xt.reshape(b, n, self.k * c))


@hookimpl
def fwk_register_convs():
    return [LSA]
