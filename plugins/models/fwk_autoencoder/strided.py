"""Strided and transposed convolutions for the fully convolutional layouts, from any conv.

A conv playing the strided role (``Conv.strided = True``, e.g. vcconv) is built with ``mode``,
``residual_rate`` and ``activation`` and does the whole step itself. Any other conv is composed
with the sampler's pooling by :class:`PooledConv`, so ``fully_convolutional`` and
``latent_vertices`` work with every registered conv.

Both compute a block as the thesis (4.4.3: "the outputs from the ELU are added to outputs from a
downsampling residual layer") and Zhou et al.'s reference (MeshConvolution, ``graphAE.py``,
``forward_one_conv_layer_batch``) do:

    y = sqrt(1 - r) act(conv(x)) + sqrt(r) res(x)            (no activation after the mix)

with act = ELU on every block but a network's last (the encoder's code, the decoder's output:
act = identity there), and y = act(conv(x)) without a residual path.
"""
from __future__ import annotations

import math

from torch import nn

from fwk.errors import RecipeError
from fwk.graph import sparse_apply, torch_sparse

from .checked import build_conv

MODES = ("down", "up")


class PooledConv(nn.Module):
    r"""A strided (``mode="down"``) or transposed (``mode="up"``) convolution composed of a conv
    without the strided role and the sampler's pooling operators.

    With D_l = ``hierarchy.down[l]`` (n_{l+1} x n_l), U_l = ``hierarchy.up[l]`` (n_l x n_{l+1})
    and conv_k the recipe's conv built at level k (c_in -> c_out):

        down (level l -> l + 1):   p = D_l x,   y = conv_{l+1}(p)
        up   (level l + 1 -> l):   p = U_l x,   y = conv_l(p)

    The activation act (``activation``: a module, or None for the identity) acts on the conv
    branch only; with a residual rate r the pooled input is mixed in after it, as vcconv's strided
    residual does (where the pooling is vcconv's own learned average over the support):

        y = sqrt(1 - r) act(conv(p)) + sqrt(r) R p          (y = act(conv(p)) without r),

    R a linear channel map c_in -> c_out (no bias) when c_in != c_out, else the identity.

    Args:
        conv (fwk.recipes.Spec): the recipe's conv (its class with ``strided = False``).
        in_channels (int): c_in.
        out_channels (int): c_out.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy.
        level (int): l (the finer of the two levels).
        mode (str): ``down`` or ``up``.
        residual_rate (float or None): r in [0, 1]; None: y = act(conv(p)).
        activation (torch.nn.Module or None): act, applied to the conv branch before the mix
            (None: the identity, e.g. a decoder's last block).

    Shapes:
        - **input:** (b, n_l, c_in) for ``down``, (b, n_{l+1}, c_in) for ``up``
        - **output:** (b, n_{l+1}, c_out) for ``down``, (b, n_l, c_out) for ``up``

    ``reset_parameters()`` resets the conv and draws R as ``torch.nn.Linear`` does. The
    conv is built (and draws its parameters) before R.
    """

    def __init__(self, conv, in_channels: int, out_channels: int, hierarchy, level: int, mode: str,
                 residual_rate: float | None = None, activation: nn.Module | None = None):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if residual_rate is not None and not 0.0 <= residual_rate <= 1.0:
            raise RecipeError(f"residual_rate: expected a number in [0, 1], got {residual_rate}")
        pool = hierarchy.down[level] if mode == "down" else hierarchy.up[level]
        self.register_buffer("pool", torch_sparse(pool))
        at = level + 1 if mode == "down" else level
        self.conv = build_conv(conv, in_channels, out_channels, hierarchy, at,
                               f"the {'strided' if mode == 'down' else 'transposed'} block from level "
                               f"{level if mode == 'down' else level + 1} (after the sampler's pooling)")
        self.r = residual_rate
        self.act = activation
        self.res_lin = (nn.Linear(in_channels, out_channels, bias=False)
                        if residual_rate is not None and in_channels != out_channels else None)

    def reset_parameters(self) -> None:
        """Reset the conv and R."""
        self.conv.reset_parameters()
        if self.res_lin is not None:
            self.res_lin.reset_parameters()

    def forward(self, x):
        p = sparse_apply(self.pool, x)
        y = self.conv(p)
        if self.act is not None:
            y = self.act(y)
        if self.r is None:
            return y
        res = self.res_lin(p) if self.res_lin is not None else p
        return math.sqrt(1 - self.r) * y + math.sqrt(self.r) * res


def strided_conv(conv, in_channels: int, out_channels: int, hierarchy, level: int, mode: str,
                 residual_rate: float | None = None, activation: nn.Module | None = None) -> nn.Module:
    """The ``mode`` ("down": level l -> l + 1, "up": l + 1 -> l) block of the recipe's conv (a
    Spec), y = sqrt(1 - r) act(conv(x)) + sqrt(r) res(x): the conv itself where it plays the
    strided role (``conv.cls.strided``; built with ``mode``, ``residual_rate`` and
    ``activation``), else a :class:`PooledConv`."""
    if conv.cls.strided:
        return build_conv(conv, in_channels, out_channels, hierarchy, level,
                          f"the {'strided' if mode == 'down' else 'transposed'} block", mode=mode,
                          residual_rate=residual_rate, activation=activation)
    return PooledConv(conv, in_channels, out_channels, hierarchy, level, mode, residual_rate, activation)
