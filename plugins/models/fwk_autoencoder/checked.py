"""Each conv of a network, built and checked where the network is assembled.

A conv plugin maps (b, n, c_in) -> (b, n', c_out) at its level (``fwk.protocols.Conv``). A
wrong channel count or vertex count would otherwise surface in the next layer, deep inside a
training step, naming neither the conv nor the level. So every conv the autoencoder networks
build (and so every network ``pb``, ``pbs`` and ``dsm`` borrow) is run once on a batch of one
zero sample as it is built, and a conv whose output has the wrong shape, or whose forward
raises, stops the build with one line naming the recipe path, the conv, the level, the block
and the shapes. The check draws no random numbers (the torch RNG state is kept) and leaves the
conv's mode (train / eval) as it was.
"""
from __future__ import annotations

import torch

from fwk.errors import PluginError

#: mode -> (input level, output level) relative to the level l a conv is built at
_LEVELS = {None: (0, 0), "same": (0, 0), "down": (0, 1), "up": (1, 0)}


def build_conv(conv, in_channels: int, out_channels: int, hierarchy, level: int, block: str, **extra):
    """``conv.build(in_channels, out_channels, hierarchy, level, **extra)`` (conv: the recipe's
    Spec), checked on a (1, n_in, in_channels) batch of zeros: the output must be
    (1, n_out, out_channels) with n_in, n_out the vertex counts of the levels the conv reads and
    writes (``extra["mode"]`` "down": level -> level + 1, "up": level + 1 -> level). ``block``
    names the conv's place in the network (``encoder block 2``) for the message."""
    module = conv.build(in_channels, out_channels, hierarchy, level, **extra)
    d_in, d_out = _LEVELS[extra.get("mode")]
    n_in = hierarchy.levels[level + d_in].n_vertices
    n_out = hierarchy.levels[level + d_out].n_vertices
    where = (f"{conv.path or 'conv'}: conv {conv.name!r} ({conv.cls.__module__}.{conv.cls.__qualname__}) "
             f"at level {level}" + (f" mode {extra['mode']}" if extra.get("mode") else "") + f", {block}")
    expected = (1, n_out, out_channels)
    x = torch.zeros(1, n_in, in_channels)
    training = module.training
    try:
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            module.train(False)
            y = module(x)
    except Exception as e:  # a conv plugin's forward can raise anything: the message names the conv
        first = (str(e).strip().splitlines() or [""])[0]
        raise PluginError(f"{where}: its forward on an input of shape {tuple(x.shape)} (expected output "
                          f"{expected}) raised {type(e).__name__}: {first}") from e
    finally:
        module.train(training)
    got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
    if got != expected:
        raise PluginError(f"{where}: maps an input of shape {tuple(x.shape)} to {got}, expected {expected} "
                          f"(b, n, c_out: {n_out} vertices, {out_channels} channels)")
    return module
