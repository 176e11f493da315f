"""Feature scaling shared by every representation (DESIGN.md "Definitions").

Normalisation (thesis eqs. 3.9-3.10 as corrected in DESIGN.md), with lo / hi the minimum /
maximum of the training features over the pooled axes (below):

    norm(F, a)   = (F - lo) / (hi - lo) * 2a - a          # into [-a, a]
    denorm(G, a) = (G + a) / (2a) * (hi - lo) + lo

Standardisation (eqs. 3.11-3.12): std(F) = (F - mean) / sigma; sigma is floored at ``eps``.

``granularity`` says over which axes the statistics pool, for both kinds (the thesis's "each
channel of all samples", eq. 3.8, admits both; Tan et al.'s mesh VAE scales each feature
dimension):

- ``"vertex"``: per vertex and channel, over the training samples;
- ``"channel"``: per channel, over the training samples and vertices;
- ``None`` (the default): the kind's own default, ``"vertex"`` for std (the reference
  implementations' choice) and ``"channel"`` for norm (DESIGN.md's first definition). Before
  issue 17 norm ignored ``granularity`` and was always per channel; ``None`` keeps that.

Options of norm only (std and none ignore them):

- ``range``: ``"minmax"`` (lo, hi the minimum and maximum, as above) or ``"quantile"`` (lo, hi
  the ``q`` and ``1 - q`` quantiles, ``numpy.quantile``'s default linear interpolation), so a
  few outliers do not set the range. Values outside [lo, hi] are **not clipped**: the map stays
  affine, so ``inverse(transform(F)) == F`` for every F, and they come out a little beyond
  [-a, a] (about 2q of the training values). The networks have no bounded output layer, and
  their loss is computed after ``inverse_torch`` (thesis table 3.2), so an outlier keeps its
  true value in the loss.
- ``centre``: ``"mid"`` (the middle of [lo, hi] maps to 0: the thesis's eq. 3.9) or ``"mean"``:
  zero maps to the training mean of the features, vertex by vertex, whatever the granularity,
  so a zero network output decodes exactly to the mean features. The half-range is then taken
  about the mean: with D = F - mean (mean per vertex and channel over the training samples),
  lo / hi are D's minimum / maximum (or quantiles) over the pooled axes and

      norm(F, a)   = (F - mean) / h * a,   h = max(hi, -lo)
      denorm(G, a) = G h / a + mean

  so the training range still lies in [-a, a] (for ``granularity: vertex`` and ``minmax``,
  h = max(max F - mean, mean - min F) per vertex and channel).

``inverse_torch`` is the differentiable inverse used to compute losses in the
representation's own unscaled space (thesis table 3.2).

Every variant is stored as one affine map, ``transform(F) = (F - shift) / div`` with ``shift``
and ``div`` of shape (n, c) (per vertex) or (1, c), broadcasting over (b, n, c) batches. A
state saved before these options existed (no ``range`` / ``centre`` keys) loads as what it was:
min-max, centred on the middle, per channel for norm.
"""
from __future__ import annotations

import numpy as np
import torch

from .errors import DataError, RecipeError
from .registry import did_you_mean

KINDS = ("none", "std", "norm")
GRANULARITIES = ("vertex", "channel")
RANGES = ("minmax", "quantile")
CENTRES = ("mid", "mean")
DEFAULT_GRANULARITY = {"none": "vertex", "std": "vertex", "norm": "channel"}


def _choice(name, value, choices):
    if value not in choices:
        raise RecipeError(f"{name}: expected one of {', '.join(choices)}, got {value!r}"
                          f"{did_you_mean(str(value), choices)}")
    return value


class Scaler:
    """Fitted feature scaling: ``kind`` none / std / norm, ``fit(F)`` on (b, n, c) training
    features, then ``transform`` / ``inverse`` (NumPy, float64) and ``inverse_torch``.
    ``granularity``, and for norm ``range`` / ``q`` / ``centre``, as in the module docstring."""

    def __init__(self, kind: str = "std", granularity: str | None = None, a: float = 1.0, eps: float = 1e-8,
                 range: str = "minmax", q: float = 0.01, centre: str = "mid"):
        if kind not in KINDS:
            raise RecipeError(f"scaling: unknown scaling {kind!r}{did_you_mean(kind, KINDS)} (choices: {', '.join(KINDS)})")
        if granularity is not None and granularity not in GRANULARITIES:
            raise RecipeError(f"granularity: expected one of {', '.join(GRANULARITIES)}, got {granularity!r}")
        if not a > 0:
            raise RecipeError(f"a: the normalisation range [-a, a] needs a > 0, got {a!r}")
        _choice("range", range, RANGES)
        _choice("centre", centre, CENTRES)
        if not 0 <= q < 0.5:
            raise RecipeError(f"q: the quantile range [q, 1 - q] needs 0 <= q < 0.5, got {q!r}")
        self.kind, self.a, self.eps = kind, float(a), float(eps)
        self.granularity = DEFAULT_GRANULARITY[kind] if granularity is None else granularity
        self.range, self.q, self.centre = range, float(q), centre
        self.shift: np.ndarray | None = None  # what is subtracted
        self.div: np.ndarray | None = None  # what it is divided by (after the shift)
        self._torch: dict = {}  # (dtype, device) -> (div, shift) tensors for inverse_torch

    @classmethod
    def like(cls, other: "Scaler") -> "Scaler":
        """An unfitted scaler with ``other``'s settings (kind, granularity, a, eps, range, q,
        centre). Fitted on features that ``other`` already scaled, it composes with it into the
        scaling of that kind fitted on the raw features (both maps are affine and increasing)."""
        return cls(other.kind, other.granularity, other.a, other.eps, other.range, other.q, other.centre)

    def _lo_hi(self, D: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
        if self.range == "minmax":
            return D.min(axis=axes), D.max(axis=axes)
        lo, hi = np.quantile(D, [self.q, 1.0 - self.q], axis=axes)
        return lo, hi

    def fit(self, F: np.ndarray) -> "Scaler":
        """Fit the scaling on training features F (b, n, c); returns self."""
        F = np.asarray(F, dtype=np.float64)
        if F.ndim != 3 or len(F) == 0:
            raise ValueError(f"Scaler.fit expects (b, n, c) features with b > 0, got shape {F.shape}")
        if not np.all(np.isfinite(F)):
            raise DataError("scaling: the training features contain NaN or infinite values")
        c = F.shape[-1]
        axes = (0,) if self.granularity == "vertex" else (0, 1)
        if self.kind == "none":
            self.shift, self.div = np.zeros((1, c)), np.ones((1, c))
        elif self.kind == "std":
            self.shift = F.mean(axis=axes).reshape(-1, c)
            self.div = np.maximum(F.std(axis=axes).reshape(-1, c), self.eps)
        elif self.centre == "mid":
            lo, hi = self._lo_hi(F, axes)
            rng = np.maximum(hi - lo, self.eps).reshape(-1, c)
            # norm = (F - lo) / rng * 2a - a = (F - (lo + rng / 2)) / (rng / (2a))
            self.shift = lo.reshape(-1, c) + rng / 2
            self.div = rng / (2 * self.a)
        else:  # centred on the per-vertex training mean, half-range about it
            mean = F.mean(axis=0)  # (n, c)
            lo, hi = self._lo_hi(F - mean, axes)
            half = np.maximum(np.maximum(hi, -lo), self.eps / 2).reshape(-1, c)
            self.shift = mean
            self.div = half / self.a
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
        """Kind, granularity, a, eps, range, q, centre and the fitted shift and div."""
        return {"kind": self.kind, "granularity": self.granularity, "a": self.a, "eps": self.eps,
                "range": self.range, "q": self.q, "centre": self.centre, "shift": self.shift, "div": self.div}

    def load_state_dict(self, d: dict) -> "Scaler":
        """Restore the state written by ``state_dict``; returns self. A state without ``range``
        (saved before issue 17) is min-max, centred on the middle, and per channel for norm."""
        self.kind, self.granularity = str(d["kind"]), str(d["granularity"])
        self.a, self.eps = float(d["a"]), float(d["eps"])
        old = "range" not in d
        self.range = "minmax" if old else str(d["range"])
        self.q = 0.0 if old else float(d["q"])
        self.centre = "mid" if old else str(d["centre"])
        if old and self.kind == "norm":
            self.granularity = "channel"  # what an old norm was, whatever granularity it was given
        self.shift, self.div = np.asarray(d["shift"]), np.asarray(d["div"])
        self._torch = {}
        return self
