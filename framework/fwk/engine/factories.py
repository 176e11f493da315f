"""``loss_module`` and ``autoencoder_module``: the call forms plugins use to build a
``LossModule`` / ``AutoencoderModule`` (``fwk.engine.modules``).

They import Lightning on their first call, not here: Lightning costs ~2.2 s of import time on
top of torch's ~1 s (measured with ``python -X importtime``), plugins import these names at
their top, and ``fwk list`` imports every plugin.
"""
from __future__ import annotations


def loss_module(modules: dict, loss):
    """A ``LossModule`` training the parameters of ``modules`` (attribute name -> nn.Module; the
    names prefix the checkpoint's keys) by ``loss(module, batch, stage)``."""
    from .modules import LossModule  # deferred: Lightning (see the module docstring)

    return LossModule(modules, loss)


def autoencoder_module(net, unscale, kl_weight: float, encode=None, decode=None):
    """An ``AutoencoderModule``: unscaled L1 + ``kl_weight`` KL of the (variational)
    autoencoder ``net`` (``encode(net, F)`` -> (mu, logvar or None), ``decode(net, z)``;
    default ``net.enc`` / ``net.dec``)."""
    from .modules import AutoencoderModule  # deferred: Lightning (see the module docstring)

    return AutoencoderModule(net, unscale, kl_weight, encode, decode)
