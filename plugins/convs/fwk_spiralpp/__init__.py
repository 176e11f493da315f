"""Conv ``spiral++``: SpiralNet++ (Gong et al. 2019, "SpiralNet++: A Fast and Highly Efficient
Mesh Convolution Operator"; thesis 3.3).

Each vertex i has a spiral S(i, l): the vertex, its one-ring in mesh (fan) order, then the
following rings, each continuing the previous one in the same rotational direction, cut to
length l (every ``dilation``-th entry of a spiral l x dilation long; ``fwk.graph.spirals``).
Spirals are fixed by the template's connectivity and do not depend on a reference vertex (a
closed one-ring starts at its smallest vertex index, an open one at its border neighbour). The convolution
concatenates the features along the spiral and applies one shared linear layer:

    x'_i = W [x_{S(i,1)} || x_{S(i,2)} || ... || x_{S(i,l)}] + b

implemented as one gather (b, n, l, c) and one matrix product. Where rings run out (borders,
small components) the spiral is padded with the centre vertex (``fwk.graph.spirals``), an
explicit choice instead of the reference code's silent k-nearest-neighbour fallback. Defaults
follow the reference: length 9, dilation 1.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from fwk.graph import spirals
from fwk.hookspecs import hookimpl

_CACHE: dict = {}


def level_spirals(hierarchy, level: int, length: int, dilation: int) -> np.ndarray:
    lv = hierarchy.levels[level]
    if lv.faces is None:
        from fwk.errors import RecipeError

        raise RecipeError("conv spiral++ needs a sampler whose levels are triangle meshes (quadric)")
    key = (lv.n_vertices, hash(np.asarray(lv.faces).tobytes()), length, dilation)
    if key not in _CACHE:
        _CACHE[key] = spirals(lv.faces, lv.n_vertices, length, dilation)
    return _CACHE[key]


class SpiralPP(nn.Module):
    """SpiralNet++ convolution (fixed-length spirals, shared linear layer)."""

    name = "spiral++"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, length: int = 9,
                 dilation: int = 1):
        super().__init__()
        idx = level_spirals(hierarchy, level, length, dilation)
        self.register_buffer("index", torch.as_tensor(idx, dtype=torch.long))
        self.length = length
        self.layer = nn.Linear(in_channels * length, out_channels)
        nn.init.xavier_uniform_(self.layer.weight)
        nn.init.zeros_(self.layer.bias)

    def forward(self, x):
        b, n, c = x.shape
        g = x[:, self.index.reshape(-1)].reshape(b, n, self.length * c)
        return self.layer(g)


@hookimpl
def fwk_register_convs():
    return [SpiralPP]
