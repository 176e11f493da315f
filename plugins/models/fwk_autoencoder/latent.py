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
(mean and log-variance halves) and c_L for an AE; z is the flattened (n_latent x c_L) map, so the
latent size is n_latent * c_L and no fully connected layer is needed. The decoder starts with the
transposed convolution from the latent level (a linear layer first only when another model feeds
it a code of a different size, e.g. Deep Spectral Meshes' concatenated Z).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path
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


class LatentConvEncoder(nn.Module):
    """Strided convolutions down to the latent level; z = the flattened (n_latent, c_L) map."""

    def __init__(self, conv, hierarchy, channels, variational, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        self.c_last, self.variational = channels[-1], variational
        outs = [*channels[1:-1], channels[-1] * (2 if variational else 1)]
        self.convs = nn.ModuleList(strided_conv(conv, channels[i], outs[i], hierarchy, i, "down", residual_rate)
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
        self.convs = nn.ModuleList(strided_conv(conv, chans[i + 1], chans[i], hierarchy, i, "up", residual_rate)
                                   for i in reversed(range(L)))
        self.act = act()

    def forward(self, z):
        x = (self.fc(z) if self.fc is not None else z).reshape(len(z), self.n_last, self.c_last)
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < len(self.convs) - 1:
                x = self.act(x)
        return x
