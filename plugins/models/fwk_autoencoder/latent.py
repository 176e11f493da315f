"""The fully convolutional latent of Zhou et al. (2020) as the thesis sizes it (section 3.4: "an
additional graph convolutional layer ... brings the latent space size to 64 (8 latent vertices x
8-dimensional features)").

A sampler's coarsest level rarely has the wanted number of vertices (the ``simple`` sampler takes
the ICT face-head 11,248 -> 3,089 -> 631 -> 106 -> 16 -> 1), so the model replaces the last level
of the hierarchy by a *latent level* of exactly ``n_latent`` vertices built from the level above:

* centres: farthest-point sampling in hop distance on that level's graph (the first centre is
  vertex 0; every unreachable vertex is infinitely far, so each connected component gets a centre
  while centres remain);
* cells: each vertex belongs to its nearest centre by hops (ties to the lower centre index);
  vertices of components without a centre go to the nearest centre in space (template positions);
* pool support P (n_latent x n): the cell of each centre plus every vertex within ``radius`` hops
  of it; ``down`` is the mean over P's rows, ``up`` the mean over P's columns (rows of P^T), and
  the neighbourhoods a strided / transposed conv reads (``Level.pool`` of the latent level,
  ``Level.unpool`` of the level above) are P's rows and columns; the latent level's own ``conv``
  support is the vertices within ``radius`` hops on its graph (centres whose supports touch).

The encoder's last strided convolution maps onto the latent level with 2 c_L channels for a VAE
(mean and log-variance halves) and c_L for an AE; z is the flattened (n_latent x c_L) map
(vertex-major: entry v c_L + c is channel c of latent vertex v), so the latent size is
n_latent * c_L and no fully connected layer is needed. The decoder starts with the transposed
convolution from the latent level, which reads a (b, n_latent, c) map:

* its own code: c = c_L;
* ``latent_parts = [d_0, d_1, ...]`` (Deep Spectral Meshes' Z = [z_0 | z_1 | ...], thesis 4.4.2,
  figure 4.1: "Z in R^{8 x 8}"): each z_j, a code of a network with the same latent level, is
  read as its (n_latent, d_j / n_latent) map and the maps are concatenated per latent vertex,
  c = sum_j d_j / n_latent; still no dense layer, so latent vertex v of every part feeds only
  the first transposed convolution's outputs in v's support;
* ``latent_in`` (a foreign flat code of another size, e.g. pb's code with a one-hot condition):
  a linear layer to the (n_latent, c_L) map first.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path
import torch
from torch import nn

from fwk.errors import RecipeError
from fwk.graph import adjacency, padded_rows, reach
from fwk.protocols import Hierarchy, Level, Neighbourhood

from .strided import strided_conv


def farthest_centres(A, n_latent: int) -> np.ndarray:
    """Greedy farthest-point sampling in hop distance (first centre 0, ties to the lower index)."""
    n = A.shape[0]
    dist = np.full(n, np.inf)
    centres = []
    nxt = 0
    for _ in range(n_latent):
        centres.append(nxt)
        d = shortest_path(A, unweighted=True, directed=False, indices=[nxt])[0]
        dist = np.minimum(dist, d)
        dist[centres] = -1.0
        nxt = int(np.argmax(dist))  # inf (another component) first; argmax takes the lowest index
    return np.asarray(centres, dtype=np.int64)


def latent_support(lv: Level, n_latent: int, radius: int):
    """(centres, P): the latent centres on level ``lv`` and the (n_latent, n) boolean pool support."""
    n = lv.n_vertices
    if n_latent > n:
        raise RecipeError(f"latent_vertices: {n_latent} latent vertices from a level of only {n} vertices; "
                          "use fewer sampler levels or fewer latent vertices")
    A = adjacency(lv.edges, n)
    C = farthest_centres(A, n_latent)
    D = shortest_path(A, unweighted=True, directed=False, indices=C)  # (n_latent, n)
    owner = np.argmin(D, axis=0)  # ties: the lower centre index
    lost = ~np.isfinite(D.min(axis=0))
    if lost.any():
        V = lv.vertices if lv.vertices is not None else np.zeros((n, 3))
        owner[lost] = np.argmin(((V[lost, None, :] - V[None, C, :]) ** 2).sum(-1), axis=1)
    cells = sp.csr_matrix((np.ones(n), (owner, np.arange(n))), shape=(n_latent, n))
    P = (cells + reach(A, radius)[C]).tocsr()
    P.data[:] = 1.0
    return C, P


def _mean_rows(P):
    P = sp.csr_matrix(P, dtype=np.float64)
    return (sp.diags(1.0 / np.maximum(np.asarray(P.sum(1)).ravel(), 1)) @ P).tocsr()


def with_latent_level(h: Hierarchy, depth: int, n_latent: int, radius: int = 2) -> Hierarchy:
    """A new hierarchy: levels 0..depth-1 of ``h`` and, as level ``depth``, a latent level of
    ``n_latent`` vertices built from level depth-1 (``h`` itself, maybe cached, is not changed)."""
    if len(h.levels) < depth:
        raise RecipeError(f"latent_vertices: {depth} down-sampling blocks need a sampler with at least {depth - 1} "
                          f"levels below the template, this one has {len(h.levels) - 1}")
    above = h.levels[depth - 1]
    C, P = latent_support(above, n_latent, radius)
    PT = P.T.tocsr()
    above = dataclasses.replace(above, unpool=Neighbourhood(*padded_rows(PT)))
    A = adjacency(above.edges, above.n_vertices)
    near = (P @ A @ P.T).tocoo()  # centres whose supports touch
    keep = near.row < near.col
    V = above.vertices[C] if above.vertices is not None else None
    E = np.stack([near.row[keep], near.col[keep]], 1).astype(np.int64)
    lat = Level(n_latent, E, None, V, pool=Neighbourhood(*padded_rows(P, first=C)), centres=C,
                conv=Neighbourhood(*padded_rows(reach(adjacency(E, n_latent), radius), first=np.arange(n_latent))))
    return Hierarchy([*h.levels[:depth - 1], above, lat], [*h.down[:depth - 1], _mean_rows(P)],
                     [*h.up[:depth - 1], _mean_rows(PT)])


def batch_major(y):
    """A decoder's result laid out batch-major (a copy only where it is not): a conv that computes vertex-major
    (vcconv's native kernels) hands on a transposed view, and the loss's and the metrics' elementwise operations on
    a view of 3 floats a vertex run strided (the L1 loss's subtraction 0.8 ms against 0.055 ms contiguous in the
    chapter 5 width's step). Every decoder ends with it (``Decoder``, ``ConvDecoder``, ``LatentConvDecoder``)."""
    return y.contiguous()


class LatentConvEncoder(nn.Module):
    """Strided convolutions down to the latent level, y = sqrt(1 - r) ELU(conv(x)) + sqrt(r) res(x)
    (no ELU on the last); z = the flattened (n_latent, c_L) map (mu, and logvar for a VAE)."""

    def __init__(self, conv, hierarchy, channels, variational, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        self.c_last, self.variational = channels[-1], variational
        outs = [*channels[1:-1], channels[-1] * (2 if variational else 1)]
        self.convs = nn.ModuleList(strided_conv(conv, channels[i], outs[i], hierarchy, i, "down", residual_rate,
                                                act() if i < L - 1 else None) for i in range(L))

    def forward(self, x):
        for conv in self.convs:
            x = conv(x)
        mu = x[..., :self.c_last].flatten(1)
        return mu, (x[..., self.c_last:].flatten(1) if self.variational else None)


class LatentConvDecoder(nn.Module):
    """Transposed convolutions from the latent level; the first reads a (b, n_latent, c) map (its
    own code, or several codes' maps concatenated per latent vertex: ``latent_parts``); a linear
    layer first only for a foreign flat code (``latent_in``). No ELU on the last block.

    ``forward(z)``: z (b, sum of the parts' sizes) flat, or the map (b, n_latent, c) itself.
    """

    def __init__(self, conv, hierarchy, channels, out_channels, act, residual_rate, latent_in: int | None = None,
                 latent_parts: list[int] | None = None):
        super().__init__()
        L = len(channels) - 1
        self.n_last, self.c_last = n, c = hierarchy.levels[L].n_vertices, channels[-1]
        self.fc = None
        if latent_parts is not None:
            bad = [d for d in latent_parts if int(d) <= 0 or int(d) % n]
            if bad:
                raise RecipeError(f"latent_parts: codes of {list(latent_parts)} entries cannot be read on {n} latent "
                                  f"vertices ({bad} not a positive multiple of {n}); the networks' latent_vertices "
                                  "must agree")
            self.parts = [int(d) // n for d in latent_parts]  # channels per latent vertex of each code
        else:
            if latent_in is not None and latent_in != n * c:
                self.fc = nn.Linear(latent_in, n * c)
            self.parts = [c]
        self.map_channels = sum(self.parts)
        chans = [out_channels, *channels[1:-1], self.map_channels]
        self.convs = nn.ModuleList(strided_conv(conv, chans[i + 1], chans[i], hierarchy, i, "up", residual_rate,
                                                act() if i > 0 else None) for i in reversed(range(L)))

    def latent_map(self, z):
        """z (b, d) -> the (b, n_latent, c) map the first transposed convolution reads."""
        if z.dim() == 3:
            return z
        b, n = len(z), self.n_last
        if self.fc is not None:
            return self.fc(z).reshape(b, n, self.c_last)
        if len(self.parts) == 1:
            return z.reshape(b, n, self.parts[0])
        codes = torch.split(z, [n * c for c in self.parts], dim=1)
        return torch.cat([x.reshape(b, n, c) for x, c in zip(codes, self.parts)], dim=2)

    def forward(self, z):
        x = self.latent_map(z)
        for conv in self.convs:
            x = conv(x)
        return batch_major(x)
