"""Conv ``feast``: FeaStNet (Verma et al. 2018, "FeaStNet: Feature-Steered Graph Convolutions
for 3D Shape Analysis"; thesis 3.3), reusing ``torch_geometric.nn.FeaStConv``.

    x'_i = b + sum_{j in N(i) u {i}} 1/|N(i)| sum_{h=1}^{H} q_h(x_i, x_j) W_h x_j,
    q_h(x_i, x_j) = softmax_h(u_h^T (x_j - x_i) + c_h)

so the assignment of neighbours to the H weight matrices is steered by the features
themselves. A batch (b, n, c) is one graph of b n nodes (the level's edge index repeated with
offsets), which FeaStConv handles in pure PyTorch.
"""
from __future__ import annotations

import torch
from torch import nn

from fwk.graph import edge_index
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


class FeaSt(nn.Module):
    r"""FeaStNet feature-steered graph convolution (torch_geometric FeaStConv).

    Over the level's edges, N(i) the neighbours of vertex i, with H weight matrices W_h:

        x'_i = b + sum_{j in N(i) u {i}} 1/|N(i) u {i}| sum_{h=1}^{H} q_h(x_i, x_j) W_h x_j,
        q_h(x_i, x_j) = softmax_h(u_h^T (x_j - x_i) + c_h)

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy (any sampler: only the
            level's ``edges`` are read).
        level (int): the level the convolution works on (stride 1).
        heads (int): H, the number of weight matrices (default 8).

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` re-draws FeaStConv's W_h and u_h (its linear layers' initialisation)
    and c, b ~ N(0, 0.1^2); FeaStConv draws them itself when it is constructed.
    """

    name = "feast"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, heads: int = 8):
        super().__init__()
        # deferred: torch_geometric adds ~1.3 s of import time (measured on top of torch) to every
        # `fwk` command that loads the plugins; only this conv needs it, when it is built
        from torch_geometric.nn import FeaStConv

        lv = hierarchy.levels[level]
        self.n = lv.n_vertices
        self.register_buffer("edges", edge_index(lv.edges, lv.n_vertices, self_loops=False))
        self.conv = FeaStConv(in_channels, out_channels, heads=heads, add_self_loops=True)  # initialises itself

    def reset_parameters(self) -> None:
        """Re-draw FeaStConv's parameters (its own ``reset_parameters``)."""
        self.conv.reset_parameters()

    def forward(self, x):
        b, n, c = x.shape
        off = (torch.arange(b, device=x.device) * n).repeat_interleave(self.edges.shape[1])
        ei = self.edges.repeat(1, b) + off
        return self.conv(x.reshape(b * n, c), ei).reshape(b, n, -1)


@hookimpl
def fwk_register_convs():
    return [FeaSt]
