"""Feature scaling shared by every representation (DESIGN.md "Definitions").

Normalisation (thesis eqs. 3.9-3.10 as corrected in DESIGN.md), per channel c, with lo / hi
the minimum / maximum of channel c over the training samples and vertices:

    norm(F, a)   = (F - lo) / (hi - lo) * 2a - a          # into [-a, a]
    denorm(G, a) = (G + a) / (2a) * (hi - lo) + lo

Standardisation (eqs. 3.11-3.12): std(F) = (F - mean) / sigma, with mean and sigma per vertex
and channel over the training samples (``granularity="vertex"``, the reference
implementations' choice) or per channel (``"channel"``); sigma is floored at ``eps``.
``inverse_torch`` is the differentiable inverse used to compute losses in the
representation's own unscaled space (thesis table 3.2).
"""
from __future__ import annotations

import numpy as np

KINDS = ("none", "std", "norm")
GRANULARITIES = ("vertex", "channel")


class Scaler:
    def __init__(self, kind: str = "std", granularity: str = "vertex", a: float = 1.0, eps: float = 1e-8):
        from .errors import RecipeError
        from .registry import did_you_mean

        if kind not in KINDS:
            raise RecipeError(f"scaling: unknown scaling {kind!r}{did_you_mean(kind, KINDS)} (choices: {', '.join(KINDS)})")
        if granularity not in GRANULARITIES:
            raise RecipeError(f"granularity: expected one of {', '.join(GRANULARITIES)}, got {granularity!r}")
        self.kind, self.granularity, self.a, self.eps = kind, granularity, float(a), float(eps)
        self.shift: np.ndarray | None = None  # what is subtracted
        self.div: np.ndarray | None = None  # what it is divided by (after the shift)

    def fit(self, F: np.ndarray) -> "Scaler":
        F = np.asarray(F, dtype=np.float64)
        c = F.shape[-1]
        if self.kind == "none":
            self.shift, self.div = np.zeros((1, c)), np.ones((1, c))
        elif self.kind == "std":
            axes = (0,) if self.granularity == "vertex" else (0, 1)
            self.shift = F.mean(axis=axes).reshape(-1, c)
            self.div = np.maximum(F.std(axis=axes).reshape(-1, c), self.eps)
        else:
            axes = (0, 1) if self.granularity == "channel" else (0, 1)
            lo = F.min(axis=axes).reshape(1, c)
            hi = F.max(axis=axes).reshape(1, c)
            rng = np.maximum(hi - lo, self.eps)
            # norm = (F - lo) / rng * 2a - a = (F - (lo + rng / 2)) / (rng / (2a))
            self.shift = lo + rng / 2
            self.div = rng / (2 * self.a)
        return self

    def transform(self, F: np.ndarray) -> np.ndarray:
        return (np.asarray(F, dtype=np.float64) - self.shift) / self.div

    def inverse(self, G: np.ndarray) -> np.ndarray:
        return np.asarray(G, dtype=np.float64) * self.div + self.shift

    def inverse_torch(self, G):
        import torch

        div = torch.as_tensor(self.div, dtype=G.dtype, device=G.device)
        shift = torch.as_tensor(self.shift, dtype=G.dtype, device=G.device)
        return G * div + shift

    def state_dict(self) -> dict:
        return {"kind": self.kind, "granularity": self.granularity, "a": self.a, "eps": self.eps,
                "shift": self.shift, "div": self.div}

    def load_state_dict(self, d: dict) -> "Scaler":
        self.kind, self.granularity = str(d["kind"]), str(d["granularity"])
        self.a, self.eps = float(d["a"]), float(d["eps"])
        self.shift, self.div = np.asarray(d["shift"]), np.asarray(d["div"])
        return self
