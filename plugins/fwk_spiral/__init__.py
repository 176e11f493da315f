"""Conv ``spiral``: the spiral convolution of Neural 3DMM (Bouritsas et al. 2019, "Neural 3D
Morphable Models: Spiral Convolutional Networks for 3D Shape Representation Learning"; thesis 3.3).

Like SpiralNet++ the features along a spiral are concatenated and mapped by one shared linear
layer, x'_i = W [x_{S(i,1)} || ... || x_{S(i,l)}] + b, but the spiral is anchored: every
vertex's one-ring starts at the neighbour closest (in hops) to a reference vertex of its
connected component (here the component's front-most vertex, largest z: the nose tip of a face
looking along +z), so the ordering is consistent over the mesh; spirals have a fixed length
and, where rings run out, are padded with -1, an index to a dummy vertex whose features are
zero. ``dilation`` takes every d-th entry of a spiral d x l long (Neural 3DMM dilates the first
and last two layers: [2, 2, 1, 1, 1]).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from fwk.graph import bfs_distance, spirals
from fwk.hookspecs import hookimpl

_CACHE: dict = {}


def anchored_spirals(lv, length: int, dilation: int) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    key = (lv.n_vertices, hash(np.asarray(lv.faces).tobytes()), length, dilation)
    if key in _CACHE:
        return _CACHE[key]
    n, e = lv.n_vertices, lv.edges
    adj = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    _, labels = connected_components(adj, directed=False)
    V = lv.vertices if lv.vertices is not None else np.zeros((n, 3))
    refs = [int(np.flatnonzero(labels == c)[np.argmax(V[labels == c, 2])]) for c in range(labels.max() + 1)]
    dist = bfs_distance(adj, refs)
    S = spirals(lv.faces, n, length, dilation, first=lambda v, ring: min(ring, key=lambda w: (dist[w], w)), pad=-1)
    _CACHE[key] = S
    return S


class Spiral(nn.Module):
    """Neural 3DMM spiral convolution (reference-anchored spirals, -1 padding to a zero vertex)."""

    name = "spiral"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, length: int = 9,
                 dilation: int = 1):
        super().__init__()
        lv = hierarchy.levels[level]
        if lv.faces is None:
            from fwk.errors import RecipeError

            raise RecipeError("conv spiral needs a sampler whose levels are triangle meshes (quadric)")
        idx = anchored_spirals(lv, length, dilation)
        idx = np.where(idx < 0, lv.n_vertices, idx)  # the dummy vertex
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.length = length
        self.layer = nn.Linear(in_channels * length, out_channels)
        nn.init.xavier_uniform_(self.layer.weight)
        nn.init.zeros_(self.layer.bias)

    def forward(self, x):
        b, n, c = x.shape
        x = torch.cat([x, x.new_zeros(b, 1, c)], dim=1)
        return self.layer(x[:, self.index.reshape(-1)].reshape(b, n, self.length * c))


@hookimpl
def fwk_register_convs():
    return [Spiral]
