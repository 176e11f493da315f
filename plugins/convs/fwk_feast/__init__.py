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


class FeaSt(nn.Module):
    """FeaStNet feature-steered graph convolution (torch_geometric FeaStConv)."""

    name = "feast"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, heads: int = 8):
        super().__init__()
        from torch_geometric.nn import FeaStConv

        lv = hierarchy.levels[level]
        self.n = lv.n_vertices
        self.register_buffer("edges", edge_index(lv.edges, lv.n_vertices, self_loops=False))
        self.conv = FeaStConv(in_channels, out_channels, heads=heads, add_self_loops=True)

    def forward(self, x):
        b, n, c = x.shape
        off = (torch.arange(b, device=x.device) * n).repeat_interleave(self.edges.shape[1])
        ei = self.edges.repeat(1, b) + off
        return self.conv(x.reshape(b * n, c), ei).reshape(b, n, -1)


@hookimpl
def fwk_register_convs():
    return [FeaSt]
