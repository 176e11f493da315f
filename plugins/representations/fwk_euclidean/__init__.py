"""Representation ``euclidean``: vertex coordinates, raw, standardised or normalised.

Thesis 3.3.8: F = P (eq. 3.14) in the evaluation space (centred, registered, scaled into
[-1, 1]); ``scaling`` applies std (eqs. 3.11-3.12, per vertex and channel) or the corrected
norm of DESIGN.md (eqs. 3.9-3.10) fitted on the training set. With ``relative: true`` the
features are offsets from a reference, F = g(P - ref): the fitted training mean by default, or
a per-sample reference such as each subject's own neutral (personalised blendshapes, thesis
5.2.1: F_expr = g(P_expression - P_neutral)).
"""
from __future__ import annotations

import numpy as np

from fwk.hookspecs import hookimpl
from fwk.scaling import Scaler


class Euclidean:
    """Vertex coordinates (3 channels), scaled none / std / norm."""

    name = "euclidean"
    channels = 3
    places_rigidly = False  # positions come back where they were
    relative_option = True  # `relative: true` takes the features against ref (an offset)
    relative = False  # the constructor's `relative` sets it per instance
    scaler: Scaler | None = None  # each instance sets its own: the scaling encode applies last

    def __init__(self, scaling: str = "std", granularity: str | None = None, a: float = 1.0, relative: bool = False,
                 eps: float = 1e-8):
        self.scaler = Scaler(scaling, granularity, a, eps)
        self.relative = relative
        self.mean: np.ndarray | None = None

    def _ref(self, ref, P):
        if not self.relative:
            return 0.0
        r = self.mean if ref is None else np.asarray(ref, dtype=np.float64)
        return r if r.ndim == P.ndim else r[None]

    def fit(self, P, ref=None, template=None) -> None:
        P = np.asarray(P, dtype=np.float64)
        self.mean = P.mean(axis=0)
        self.scaler.fit(P - self._ref(ref, P))

    def encode(self, P, ref=None) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64)
        return self.scaler.transform(P - self._ref(ref, P)).astype(np.float32)

    def decode(self, F, ref=None, target=None) -> np.ndarray:
        F = np.asarray(F, dtype=np.float64)
        return self.scaler.inverse(F) + self._ref(ref, F)

    def unscale(self, F):
        return self.scaler.inverse_torch(F)

    def state_dict(self) -> dict:
        return {"scaler": self.scaler.state_dict(), "mean": self.mean, "relative": self.relative}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        self.scaler.load_state_dict(d["scaler"])
        self.mean = None if d["mean"] is None else np.asarray(d["mean"])
        self.relative = bool(d["relative"])


@hookimpl
def fwk_register_representations():
    return [Euclidean]
