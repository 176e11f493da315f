"""An example third-party conv: the Chebyshev spectral graph convolution (Defferrard et al. 2016,
"Convolutional Neural Networks on Graphs with Fast Localized Spectral Filtering"), the conv of
CoMA (Ranjan et al. 2018).

A filter is a polynomial of degree K - 1 in the graph Laplacian, written in the Chebyshev basis,
so it reaches K - 1 hops and needs only sparse products with the Laplacian. On a level's graph
(its ``edges``) with adjacency A and degrees D, the normalised Laplacian is
L = I - D^{-1/2} A D^{-1/2}; with lambda_max = 2 (its bound) the scaled Laplacian
L~ = 2 L / lambda_max - I = -D^{-1/2} A D^{-1/2} has its spectrum in [-1, 1]. Then

    T_0 = x,   T_1 = L~ x,   T_k = 2 L~ T_{k-1} - T_{k-2},
    x' = sum_{k=0}^{K-1} T_k Theta_k + b,

with one c_in x c_out matrix Theta_k per order. A vertex without edges has a zero row in L~.
Registered through this package's own entry point (``pyproject.toml``:
``[project.entry-points.fwk] example-cheb = "fwk_example_plugin.cheb"``).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from fwk.errors import RecipeError
from fwk.graph import sparse_apply, symmetric_adjacency, torch_sparse
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


def scaled_laplacian(edges: np.ndarray, n: int) -> sp.csr_matrix:
    """L~ = -D^{-1/2} A D^{-1/2} of an undirected edge list (0/1 adjacency), (n, n) CSR."""
    A = symmetric_adjacency(edges, n)
    A.data[:] = 1.0
    d = np.asarray(A.sum(axis=1)).ravel()
    s = np.where(d > 0, 1.0 / np.sqrt(np.maximum(d, 1e-300)), 0.0)
    return (-(sp.diags(s) @ A @ sp.diags(s))).tocsr()


class ChebConv(nn.Module):
    r"""Chebyshev spectral graph convolution (Defferrard et al. 2016; CoMA's conv).

    With L~ = -D^{-1/2} A D^{-1/2} the scaled Laplacian of the level's graph:

        T_0 = x,  T_1 = L~ x,  T_k = 2 L~ T_{k-1} - T_{k-2},    x' = sum_{k<K} T_k Theta_k + b

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy (any sampler: only the
            level's ``edges`` are read).
        level (int): the level the convolution works on (stride 1).
        k (int): K, the number of Chebyshev terms (filters reach K - 1 hops; CoMA: 6).

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` draws each Theta_k Xavier-uniform and sets b = 0.
    """

    name = "cheb"
    build_args = CONV_BUILD_ARGS
    strided = False  # a stride-1 conv: fully convolutional models pool with the sampler's operators

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, k: int = 6):
        super().__init__()
        if k < 1:
            raise RecipeError(f"k: at least one Chebyshev term, got {k}")
        lv = hierarchy.levels[level]
        self.register_buffer("lap", torch_sparse(scaled_laplacian(lv.edges, lv.n_vertices)))
        self.weight = nn.Parameter(torch.empty(k, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Theta_k Xavier-uniform (each c_in x c_out), b = 0."""
        with torch.no_grad():
            for theta in self.weight:
                nn.init.xavier_uniform_(theta)
            self.bias.zero_()

    def forward(self, x):
        t0, out = x, x @ self.weight[0]
        if len(self.weight) > 1:
            t1 = sparse_apply(self.lap, x)
            out = out + t1 @ self.weight[1]
            for theta in self.weight[2:]:
                t0, t1 = t1, 2 * sparse_apply(self.lap, t1) - t0
                out = out + t1 @ theta
        return out + self.bias


@hookimpl
def fwk_register_convs():
    return [ChebConv]
