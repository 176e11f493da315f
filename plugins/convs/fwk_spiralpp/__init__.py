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

from fwk.errors import RecipeError
from fwk.cache import content_key, memo
from fwk.graph import spirals
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


def level_spirals(hierarchy, level: int, length: int, dilation: int) -> np.ndarray:
    """(n, length) spirals of a level's triangle mesh, computed once per topology and setting."""
    lv = hierarchy.levels[level]
    if lv.faces is None:
        raise RecipeError("conv spiral++ needs a sampler whose levels are triangle meshes (quadric)")
    return memo(f"{__name__}.spirals", content_key(lv.n_vertices, np.asarray(lv.faces), length, dilation),
                lambda: spirals(lv.faces, lv.n_vertices, length, dilation))


class SpiralPP(nn.Module):
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
        idx = level_spirals(hierarchy, level, length, dilation)
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


@hookimpl
def fwk_register_convs():
    return [SpiralPP]
