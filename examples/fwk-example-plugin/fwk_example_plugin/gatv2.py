r"""An example third-party conv that wraps a PyTorch Geometric layer: GATv2 (Brody, Alon and
Yahav 2022, "How Attentive are Graph Attention Networks?", ICLR), PyG's
``torch_geometric.nn.GATv2Conv``.

GATv2 is graph attention with *dynamic* attention. For a vertex i with neighbours N(i) (the
level's edges, and i itself: a self loop), H heads, and per head h the weights W_l^h, W_r^h
(c_in -> C) and the attention vector a^h (C):

    e_ij^h = a^h . LeakyReLU(W_r^h x_i + W_l^h x_j)                   (GATv2's scoring function)
    alpha_ij^h = exp(e_ij^h) / sum_{k in N(i) + {i}} exp(e_ik^h)      (softmax over i's neighbours)
    x'_i = ||_h  sum_{j in N(i) + {i}} alpha_ij^h W_l^h x_j  + b      (heads concatenated, H C = c_out)
      or  (1/H) sum_h sum_j alpha_ij^h W_l^h x_j + b                  (heads averaged, C = c_out)

(W_l, W_r carry biases, as PyG's ``Linear``s do.) GAT (Velickovic et al. 2018) scores
e_ij = LeakyReLU(a . [W x_i || W x_j]) = LeakyReLU(a_1 . W x_i + a_2 . W x_j): as LeakyReLU is
monotone, its ranking of the neighbours j is the same for every query i ("static" attention);
GATv2 applies the non-linearity before the dot product with a, so the ranking depends on i
("dynamic" attention; W [x_i || x_j] = W_r x_i + W_l x_j in the paper's notation). GAT's hidden layers concatenate their heads; its output layer
averages them.

How a PyG layer becomes an fwk conv (the pattern, in ``BatchedMessagePassing`` below): a PyG
``MessagePassing`` layer maps node features (N, c) and an ``edge_index`` (2, E) (row 0 the
source j, row 1 the target i of each message) to (N, c'); an fwk conv maps a batch (b, n, c_in)
of signals on one fixed graph, the level's, to (b, n, c_out). So

1. build the level's ``edge_index`` once, in the constructor, from ``hierarchy.levels[level].edges``
   (each undirected edge in both directions, plus the self loops the layer wants:
   ``fwk.graph.edge_index``) and keep it as a buffer (``.to(device)`` moves it);
2. in ``forward``, read the batch as one graph of b disjoint copies: x (b, n, c) -> (b n, c),
   copy s of the edges offset by s n (built once per batch size and device, then cached), run
   the layer, reshape (b n, c') -> (b, n, c'). Messages never cross copies, so every sample is
   independent of the others (fwk's conv contract checks it).

Here the self loops are in the stored ``edge_index`` and the layer is built with
``add_self_loops=False``: the same maths as PyG's default (which removes and re-adds the self
loops on every call), without that work per forward. Registered through this package's own entry
point (``pyproject.toml``: ``[project.entry-points.fwk] example-gatv2 = "fwk_example_plugin.gatv2"``).
"""
from __future__ import annotations

import torch
from torch import nn
from torch_geometric.nn import GATv2Conv as PygGATv2Conv
from torch_geometric.nn import MessagePassing

from fwk.errors import RecipeError
from fwk.graph import edge_index as level_edge_index
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


class BatchedMessagePassing(nn.Module):
    """Runs a PyG ``MessagePassing`` layer on a batch (b, n, c) of signals on one fixed graph.

    ``layer`` is any PyG layer called as ``layer(x, edge_index)`` with x (N, c) -> (N, c');
    ``edge_index`` (2, E) int64 the graph of one sample on ``n`` vertices, with whatever self
    loops the layer expects (``fwk.graph.edge_index(edges, n, self_loops=...)``). The batch runs as
    one graph of b disjoint copies (copy s's vertices offset by s n), so samples never exchange
    messages; the batched edge index is built once per (batch size, device) and cached (a few
    sizes: training batches, the last partial one, evaluation). Subclass it, or wrap a layer
    directly::

        conv = BatchedMessagePassing(SAGEConv(c_in, c_out), fwk.graph.edge_index(lv.edges, lv.n_vertices, False),
                                     lv.n_vertices)
        y = conv(x)                                  # (b, n, c_in) -> (b, n, c_out)
    """

    #: batch sizes whose batched edge index is kept (oldest dropped first)
    CACHED_BATCH_SIZES = 8

    def __init__(self, layer: MessagePassing, edge_index: torch.Tensor, n: int):
        super().__init__()
        self.layer = layer
        self.n = int(n)
        # derived from the hierarchy (rebuilt by the constructor): not part of a checkpoint
        self.register_buffer("edge_index", edge_index.to(torch.long), persistent=False)
        self._batched: dict = {}

    def batched_edge_index(self, b: int) -> torch.Tensor:
        """(2, b E): the edges of b disjoint copies of the graph, copy s offset by s n."""
        ei = self.edge_index
        key = (int(b), ei.device)
        out = self._batched.get(key)
        if out is None:
            offsets = torch.arange(b, device=ei.device, dtype=ei.dtype) * self.n
            out = (ei[:, None, :] + offsets[None, :, None]).reshape(2, -1)
            if len(self._batched) >= self.CACHED_BATCH_SIZES:
                self._batched.pop(next(iter(self._batched)))
            self._batched[key] = out
        return out

    def _apply(self, fn, *args, **kwargs):
        self._batched.clear()  # .to(device) / .cuda(): the cached indices are rebuilt where they are used
        return super()._apply(fn, *args, **kwargs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        if n != self.n:
            raise ValueError(f"{type(self).__name__}: expected (b, {self.n}, c) input, got {tuple(x.shape)}")
        y = self.layer(x.reshape(b * n, c), self.batched_edge_index(b))
        return y.reshape(b, n, -1)

    def reset_parameters(self) -> None:
        """The wrapped layer's own ``reset_parameters()`` (PyG's convention)."""
        self.layer.reset_parameters()


class GATv2(BatchedMessagePassing):
    r"""GATv2 graph attention (Brody et al. 2022): PyG's GATv2Conv on each level's graph.

    Per head h, over i's neighbours and i itself (the level's ``edges`` and a self loop):

        e_ij = a . LeakyReLU(W_r x_i + W_l x_j),   alpha_ij = softmax_j(e_ij),
        x'_i = ||_h sum_j alpha_ij^h W_l^h x_j + b   (or the mean over heads)

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy (any sampler: only the
            level's ``edges`` are read).
        level (int): the level the convolution works on (stride 1).
        heads (int): H, the number of attention heads.
        concat (bool or None): how c_out is shared by the heads: ``true`` concatenates them,
            each head c_out / H channels (H must divide c_out); ``false`` averages them, each
            head c_out channels; ``null`` (default) concatenates where H divides c_out and
            averages otherwise (GAT's own rule: hidden layers concatenate, its output layer of
            a few channels averages).
        negative_slope (float): the LeakyReLU's slope for negative inputs (0.2, as the paper).
        dropout (float): the probability of dropping an attention coefficient alpha_ij while
            training (0: none; in [0, 1)).
        share_weights (bool): W_l = W_r (one linear map for source and target).

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` redraws PyG's initialisation: W_l, W_r and a Glorot-uniform, the
    biases of W_l and W_r uniform in +-1/sqrt(c_in) (PyG's ``Linear``), b zero.
    """

    name = "gatv2"
    build_args = CONV_BUILD_ARGS
    strided = False  # a stride-1 conv: fully convolutional models pool with the sampler's operators

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, heads: int = 1,
                 concat: bool | None = None, negative_slope: float = 0.2, dropout: float = 0.0,
                 share_weights: bool = False):
        if isinstance(heads, bool) or not isinstance(heads, int) or heads < 1:
            raise RecipeError(f"heads: at least one attention head, got {heads!r}")
        if concat is True and out_channels % heads:
            raise RecipeError(f"heads: {heads} heads do not divide {out_channels} output channels, which "
                              "concat: true shares between them (concat: false averages the heads instead, "
                              "concat: null concatenates only where they divide)")
        if not 0.0 <= float(dropout) < 1.0:
            raise RecipeError(f"dropout: a probability in [0, 1), got {dropout}")
        if float(negative_slope) < 0.0:
            raise RecipeError(f"negative_slope: at least 0, got {negative_slope}")
        cat = out_channels % heads == 0 if concat is None else bool(concat)
        per_head = out_channels // heads if cat else out_channels
        lv = hierarchy.levels[level]
        layer = PygGATv2Conv(in_channels, per_head, heads=heads, concat=cat, negative_slope=float(negative_slope),
                             dropout=float(dropout), add_self_loops=False, share_weights=bool(share_weights))
        # both directions of every edge and one self loop per vertex, built once (a buffer)
        super().__init__(layer, level_edge_index(lv.edges, lv.n_vertices, self_loops=True), lv.n_vertices)
        self.heads, self.concat = heads, cat
        self.reset_parameters()


@hookimpl
def fwk_register_convs():
    return [GATv2]
