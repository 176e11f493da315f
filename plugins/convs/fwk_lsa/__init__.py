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

from fwk.errors import RecipeError
from fwk.graph import neighbourhoods
from fwk.hookspecs import hookimpl


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
    """LSA-3DMM local structure-aware adaptive convolution (per-vertex K x K weighting)."""

    name = "lsa"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")

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
        if self.tiny:
            if lv.vertices is not None:
                phi = fourier_features(lv.vertices, idx)
            else:  # no positions on this level: learned per-vertex features instead
                phi = torch.zeros(n, 128)
            self.register_buffer("phi", phi)
            self.mix = nn.Linear(phi.shape[1], basis)
            self.temp = nn.Linear(phi.shape[1], 1)
            self.bases = nn.Parameter(torch.eye(k).repeat(basis, 1, 1))
            if lv.vertices is None:
                self.phi_free = nn.Parameter(0.01 * torch.randn(n, phi.shape[1]))
            self.A = None
        else:
            self.A = nn.Parameter(torch.eye(k).repeat(n, 1, 1))
        self.layer = nn.Linear(in_channels * k, out_channels)

    def weights(self) -> torch.Tensor:
        """(n, K, K) the per-vertex matrices A_i."""
        if self.A is not None:
            return self.A
        phi = self.phi + self.phi_free if hasattr(self, "phi_free") else self.phi
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
