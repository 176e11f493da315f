"""The reconstruction loss every built-in autoencoder trains with: ``l1_mean(a, b)`` = mean |a - b| (thesis
table 3.2), one native pass forward and one backward where ``fwk.native.ops``' kernels apply (the same gradient
as ``torch.abs(a - b).mean()``, float for float), that torch expression elsewhere."""
from __future__ import annotations

from fwk.native.ops import l1_mean

__all__ = ["l1_mean"]
