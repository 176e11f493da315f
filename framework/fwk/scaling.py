"""Feature scaling shared by every representation (DESIGN.md "Definitions").

Normalisation (thesis eqs. 3.9-3.10 as corrected in DESIGN.md), per channel c, with lo / hi
the minimum / maximum of channel c over the training samples and vertices:

    norm(F, a)   = (F - lo) / (hi - lo) * 2a - a          # into [-a, a]
    denorm(G, a) = (G + a) / (2a) * (hi - lo) + lo

Standardisation (eqs. 3.11-3.12): std(F) = (F - mean) / sigma, with mean and sigma per vertex
and channel over the training samples (``granularity="vertex"``, the reference
implementations' choice) or per channel (``"channel"``); sigma is floored at ``eps``.
``granularity`` applies to std only: norm is always per channel, as DESIGN.md defines it.
``inverse_torch`` is the differentiable inverse used to compute losses in the
representation's own unscaled space (thesis table 3.2).

Both are stored as one affine map, ``transform(F) = (F - shift) / div`` with ``shift`` and
``div`` of shape (n, c) (per vertex) or (1, c), broadcasting over (b, n, c) batches.
"""
from __future__ import annotations

import numpy as np
import torch

from .errors import DataError, RecipeError
from .registry import did_you_mean

KINDS = ("none", "std", "norm")
GRANULARITIES = ("vertex", "channel")


class Scaler:
    """Fitted feature scaling: ``kind`` none / std / norm, ``fit(F)`` on (b, n, c) training
    features, then ``transform`` / ``inverse`` (NumPy, float64) and ``inverse_torch``."""

    def __init__(self, kind: str = "std", granularity: str = "vertex", a: float = 1.0, eps: float = 1e-8):
        if kind not in KINDS:
            raise RecipeError(f"scaling: unknown scaling {kind!r}{did_you_mean(kind, KINDS)} (choices: {', '.join(KINDS)})")
        if granularity not in GRANULARITIES:
            raise RecipeError(f"granularity: expected one of {', '.join(GRANULARITIES)}, got {granularity!r}")
        if not a > 0:
            raise RecipeError(f"a: the normalisation range [-a, a] needs a > 0, got {a!r}")
        self.kind, self.granularity, self.a, self.eps = kind, granularity, float(a), float(eps)
        self.shift: np.ndarray | None = None  # what is subtracted
        self.div: np.ndarray | None = None  # what it is divided by (after the shift)
        self._torch: dict = {}  # (dtype, device) -> (div, shift) tensors for inverse_torch

    def fit(self, F: np.ndarray) -> "Scaler":
        """Fit the scaling on training features F (b, n, c); returns self."""
        F = np.asarray(F, dtype=np.float64)
        if F.ndim != 3 or len(F) == 0:
            raise ValueError(f"Scaler.fit expects (b, n, c) features with b > 0, got shape {F.shape}")
        if not np.all(np.isfinite(F)):
            raise DataError("scaling: the training features contain NaN or infinite values")
        c = F.shape[-1]
        if self.kind == "none":
            self.shift, self.div = np.zeros((1, c)), np.ones((1, c))
        elif self.kind == "std":
            axes = (0,) if self.granularity == "vertex" else (0, 1)
            self.shift = F.mean(axis=axes).reshape(-1, c)
            self.div = np.maximum(F.std(axis=axes).reshape(-1, c), self.eps)
        else:  # per channel over samples and vertices
            lo = F.min(axis=(0, 1)).reshape(1, c)
            hi = F.max(axis=(0, 1)).reshape(1, c)
            rng = np.maximum(hi - lo, self.eps)
            # norm = (F - lo) / rng * 2a - a = (F - (lo + rng / 2)) / (rng / (2a))
            self.shift = lo + rng / 2
            self.div = rng / (2 * self.a)
        self._torch = {}
        return self

    def _check(self):
        if self.shift is None:
            raise RuntimeError("Scaler used before fit() or load_state_dict()")

    def transform(self, F: np.ndarray) -> np.ndarray:
        """(F - shift) / div, float64."""
        self._check()
        return (np.asarray(F, dtype=np.float64) - self.shift) / self.div

    def inverse(self, G: np.ndarray) -> np.ndarray:
        """G * div + shift, float64."""
        self._check()
        return np.asarray(G, dtype=np.float64) * self.div + self.shift

    def inverse_torch(self, G):
        """The inverse on a tensor, differentiable, in G's dtype and device."""
        self._check()
        key = (G.dtype, G.device)
        if key not in self._torch:
            self._torch[key] = (torch.as_tensor(self.div, dtype=G.dtype, device=G.device),
                                torch.as_tensor(self.shift, dtype=G.dtype, device=G.device))
        div, shift = self._torch[key]
        return G * div + shift

    def state_dict(self) -> dict:
        """Kind, granularity, a, eps and the fitted shift and div."""
        return {"kind": self.kind, "granularity": self.granularity, "a": self.a, "eps": self.eps,
                "shift": self.shift, "div": self.div}

    def load_state_dict(self, d: dict) -> "Scaler":
        """Restore the state written by ``state_dict``; returns self."""
        self.kind, self.granularity = str(d["kind"]), str(d["granularity"])
        self.a, self.eps = float(d["a"]), float(d["eps"])
        self.shift, self.div = np.asarray(d["shift"]), np.asarray(d["div"])
        self._torch = {}
        return self
