"""Strided and transposed convolutions for the fully convolutional layouts, from any conv.

A conv playing the strided role (``Conv.strided = True``, e.g. vcconv) is built with ``mode`` and
``residual_rate`` and does the whole step itself. Any other conv is composed with the sampler's
pooling by :class:`PooledConv`, so ``fully_convolutional`` and ``latent_vertices`` work with every
registered conv.
"""
from __future__ import annotations

import math

from torch import nn

from fwk.errors import RecipeError
from fwk.graph import sparse_apply, torch_sparse

MODES = ("down", "up")


class PooledConv(nn.Module):
    r"""A strided (``mode="down"``) or transposed (``mode="up"``) convolution composed of a conv
    without the strided role and the sampler's pooling operators.

    With D_l = ``hierarchy.down[l]`` (n_{l+1} x n_l), U_l = ``hierarchy.up[l]`` (n_l x n_{l+1})
    and conv_k the recipe's conv built at level k (c_in -> c_out):

        down (level l -> l + 1):   p = D_l x,   y = conv_{l+1}(p)
        up   (level l + 1 -> l):   p = U_l x,   y = conv_l(p)

    With a residual rate r the pooled input is mixed in, as vcconv's strided residual does (where
    the pooling is vcconv's own learned average over the support):

        y = sqrt(1 - r) conv(p) + sqrt(r) R p,

    R a linear channel map c_in -> c_out (no bias) when c_in != c_out, else the identity.

    Args:
        conv (fwk.recipes.Spec): the recipe's conv (its class with ``strided = False``).
        in_channels (int): c_in.
        out_channels (int): c_out.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy.
        level (int): l (the finer of the two levels).
        mode (str): ``down`` or ``up``.
        residual_rate (float or None): r in [0, 1]; None: y = conv(p).

    Shapes:
        - **input:** (b, n_l, c_in) for ``down``, (b, n_{l+1}, c_in) for ``up``
        - **output:** (b, n_{l+1}, c_out) for ``down``, (b, n_l, c_out) for ``up``

    ``reset_parameters()`` resets the conv and draws R as ``torch.nn.Linear`` does. The
    conv is built (and draws its parameters) before R.
    """

    def __init__(self, conv, in_channels: int, out_channels: int, hierarchy, level: int, mode: str,
                 residual_rate: float | None = None):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if residual_rate is not None and not 0.0 <= residual_rate <= 1.0:
            raise RecipeError(f"residual_rate: expected a number in [0, 1], got {residual_rate}")
        pool = hierarchy.down[level] if mode == "down" else hierarchy.up[level]
        self.register_buffer("pool", torch_sparse(pool))
        self.conv = conv.build(in_channels, out_channels, hierarchy, level + 1 if mode == "down" else level)
        self.r = residual_rate
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
        if self.r is None:
            return y
        res = self.res_lin(p) if self.res_lin is not None else p
        return math.sqrt(1 - self.r) * y + math.sqrt(self.r) * res


def strided_conv(conv, in_channels: int, out_channels: int, hierarchy, level: int, mode: str,
                 residual_rate: float | None = None) -> nn.Module:
    """The ``mode`` ("down": level l -> l + 1, "up": l + 1 -> l) convolution of the recipe's conv
    (a Spec): the conv itself where it plays the strided role (``conv.cls.strided``), else a
    :class:`PooledConv`."""
    if conv.cls.strided:
        return conv.build(in_channels, out_channels, hierarchy, level, mode=mode, residual_rate=residual_rate)
    return PooledConv(conv, in_channels, out_channels, hierarchy, level, mode, residual_rate)
