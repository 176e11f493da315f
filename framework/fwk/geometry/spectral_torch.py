"""Spectral projection in torch: batched, differentiable, on CPU or GPU (training-time use).

The same operators as ``fwk.geometry.spectral.SpectralProjector`` without any n x n matrix:
``project(P, lo, hi) = U[:, lo:hi] (U[:, lo:hi]^T (M P))`` for P (b, n, 3), as two dense
products with the batch folded into the columns. ``assemble`` is thesis eq. 4.15 / 5.10 for
any number of bands (see the ``spectral`` assembler for the definition of the bands).
"""
from __future__ import annotations

import numpy as np
import torch


class TorchSpectralProjector(torch.nn.Module):
    """Projection onto ranges of an M-orthonormal eigenbasis U (n, K); buffers move with .to()."""

    def __init__(self, U: np.ndarray, mass: np.ndarray | None = None, dtype=torch.float32):
        super().__init__()
        U = np.asarray(U, dtype=np.float64)
        UtM = (U * np.asarray(mass, dtype=np.float64).reshape(-1)[:, None]).T if mass is not None else U.T
        self.register_buffer("U", torch.as_tensor(np.ascontiguousarray(U), dtype=dtype))
        self.register_buffer("UtM", torch.as_tensor(np.ascontiguousarray(UtM), dtype=dtype))

    @staticmethod
    def _cols(P):
        b, n, c = P.shape
        return P.permute(1, 0, 2).reshape(n, b * c), (b, n, c)

    def coefficients(self, P, lo: int = 0, hi: int | None = None):
        """(b, n, 3) -> (b, hi - lo, 3) spectral coefficients U^T M P."""
        cols, (b, n, c) = self._cols(P)
        return (self.UtM[lo:hi] @ cols).reshape(-1, b, c).permute(1, 0, 2)

    def project(self, P, lo: int = 0, hi: int | None = None):
        """(b, n, 3) -> (b, n, 3): the part of P in eigenvectors lo..hi-1."""
        cols, (b, n, c) = self._cols(P)
        out = self.U[:, lo:hi] @ (self.UtM[lo:hi] @ cols)
        return out.reshape(n, b, c).permute(1, 0, 2)

    def low(self, P, k: int):
        """The first k eigenvectors' part of P (b, n, 3)."""
        return self.project(P, 0, k)

    def high(self, P, k: int):
        """P minus its low part."""
        return P - self.project(P, 0, k)

    def assemble(self, bands, cuts, mean):
        """Eq. 4.15 / 5.10: band j (j < B) keeps its part in U[:, k_{j-1}:k_j], the last band
        everything above the last cut; ``mean`` (n, 3) is removed from each band and added once."""
        # = sum_j X_j (b_j - b_B) + b_B: each eigen-slice applied once (mean cancels; kept in
        # the signature so callers state which mean the bands are centred on)
        edges = [0, *cuts]
        last = bands[-1]
        out = last
        for j, b in enumerate(bands[:-1]):
            out = out + self.project(b - last, edges[j], edges[j + 1])
        return out
