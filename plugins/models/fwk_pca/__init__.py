"""Model ``pca``: the linear 3D morphable model (Blanz & Vetter 1999; thesis 2.1).

Training shapes are encoded by a representation (default ``euclidean``, no scaling) and
flattened to vectors x_i in R^{nc}. With the mean mu and the centred data matrix
X = [x_1 - mu, ...], the model keeps the top-K right singular vectors W (K x nc) of X and the
singular values s: encode(x) = W (x - mu), decode(z) = mu + W^T z, sample z ~ N(0, diag(s^2 /
(m - 1))). The SVD is taken of the small Gram matrix X X^T when there are fewer samples than
coordinates (always the case for meshes), so it costs O(m^2 nc), not O(m (nc)^2); with more
samples than ``GRAM_MAX`` a truncated SVD (scipy's ``svds``, ARPACK) computes only the top K.

``n_components: 0`` is the mean-shape baseline: every reconstruction and sample is mu, the
training mean (what a model must beat to have learnt anything about a subject). m training
shapes carry at most m - 1 components of non-zero variance: a larger ``n_components`` is
refused when fitting (before any other work on the data), naming the training set's size;
the default (none given) keeps min(64, m - 1).
"""
from __future__ import annotations

from typing import Annotated

import numpy as np
from scipy.sparse.linalg import svds

from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT
from fwk.recipes import Kind, Spec, make_spec

GRAM_MAX = 4000  # samples up to which the (m x m) Gram matrix is eigendecomposed densely
DEFAULT_COMPONENTS = 64  # kept when the recipe gives none (and the training set carries as many)


def top_singular(X: np.ndarray, k: int):
    """Top-k singular values s (descending) and right singular vectors W (k x d) of X (m x d)."""
    m, d = X.shape
    if min(m, d) <= GRAM_MAX:
        if m <= d:
            evals, evecs = np.linalg.eigh(X @ X.T)
            order = np.argsort(evals)[::-1][:k]
            s = np.sqrt(np.clip(evals[order], 0, None))
            keep = s > (s.max() if len(s) else 0) * 1e-10
            s, U = s[keep], evecs[:, order][:, keep]
            return s, (U / s).T @ X
        evals, evecs = np.linalg.eigh(X.T @ X)
        order = np.argsort(evals)[::-1][:k]
        s = np.sqrt(np.clip(evals[order], 0, None))
        keep = s > (s.max() if len(s) else 0) * 1e-10
        return s[keep], evecs[:, order][:, keep].T
    k = min(k, min(m, d) - 1)
    _, s, Wt = svds(X, k=k, random_state=0)
    order = np.argsort(s)[::-1]
    s, Wt = s[order], Wt[order]
    keep = s > (s.max() if len(s) else 0) * 1e-10
    return s[keep], Wt[keep]


class PCA:
    """Linear 3DMM: principal components of the training shapes."""

    name = "pca"
    task_family = RECONSTRUCT

    def __init__(self, n_components: int | None = None,
                 representation: Annotated[Spec, Kind("representation")] = {"name": "euclidean", "scaling": "none"}):
        if n_components is not None and (not isinstance(n_components, int) or isinstance(n_components, bool)
                                         or n_components < 0):
            raise RecipeError(f"n_components: expected an integer >= 0 (0: the mean shape), got {n_components!r}")
        self.n_components = n_components
        self.representation_spec = make_spec("representation", representation, "representation")
        self.rep = None
        self.mean = self.components = self.singular_values = None
        self.n_train = 0

    def _make_rep(self, ctx=None):
        return self.representation_spec.build()

    @property
    def latent_size(self) -> int:
        """The number of components kept: ``n_components`` (64 when none given) until fit, then
        at most the number of training shapes - 1 (components of zero variance are dropped)."""
        if self.components is not None:
            return int(len(self.components))
        return DEFAULT_COMPONENTS if self.n_components is None else self.n_components

    def check_data(self, data) -> None:
        """Raise a RecipeError (before any fitting) when ``n_components`` asks for more
        components than the training shapes of ``data`` (a ``FitData``) carry: m - 1."""
        self._components_for(len(data.stack("train")))

    def _components_for(self, n_train: int) -> int:
        """The number of components to compute from ``n_train`` training shapes (see
        ``check_data``)."""
        most = max(n_train - 1, 0)
        if self.n_components is None:
            return min(DEFAULT_COMPONENTS, most)
        if self.n_components > most:
            raise RecipeError(f"n_components: {self.n_components} components, but the training split holds "
                              f"{n_train} meshes, which carry at most {most}; give n_components <= {most} "
                              f"(or leave it out: min(64, training meshes - 1))")
        return self.n_components

    def fit(self, data, ctx=None) -> None:
        """Principal components of ``data.stack("train")`` (a ``FitData``)."""
        P = data.stack("train")
        if len(P) == 0:
            raise DataError("pca: the training split holds no shapes")
        n_wanted = self._components_for(len(P))
        self.rep = self._make_rep(ctx)
        self.rep.fit(P, None, data.template)
        F = self.rep.encode(P).astype(np.float64).reshape(len(P), -1)
        self.mean = F.mean(axis=0)
        X = F - self.mean
        k = int(min(n_wanted, X.shape[1]))
        # right singular vectors (k, nc); components of zero variance are dropped
        if k == 0:  # n_components 0: the mean shape
            self.singular_values, self.components = np.zeros(0), np.zeros((0, X.shape[1]))
        else:
            self.singular_values, self.components = top_singular(X, k)
        self.n_train = len(P)
        self._shape = P.shape[1:]
        self._channels = F.shape[1] // P.shape[1]

    def encode(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, latent_size) coefficients W (x - mu)."""
        F = self.rep.encode(np.asarray(P, dtype=np.float64)).astype(np.float64).reshape(len(P), -1)
        return (F - self.mean) @ self.components.T

    def decode(self, z) -> np.ndarray:
        """(b, latent_size) -> (b, n, 3): mu + W^T z, decoded by the representation."""
        F = self.mean + np.asarray(z, dtype=np.float64) @ self.components
        return self.rep.decode(F.reshape(len(F), self._shape[0], self._channels))

    def reconstruct(self, P) -> np.ndarray:
        """Project and decode; representations that lose position (dr) are registered to P."""
        F = self.mean + self.encode(P) @ self.components
        return self.rep.decode(F.reshape(len(F), self._shape[0], self._channels), None, P)

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n meshes decoded from z ~ N(0, diag(s^2 / (m - 1))) (deterministic for a seed)."""
        rng = np.random.default_rng(seed)
        sd = self.singular_values / np.sqrt(max(self.n_train - 1, 1))
        return self.decode(rng.standard_normal((n, len(sd))) * sd)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "components": self.components, "singular_values": self.singular_values,
                "n_train": self.n_train, "shape": self._shape, "channels": self._channels,
                "rep": self.rep.state_dict(), "rep_name": self.rep.name}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a fitted model (``ctx`` is passed on to the representation)."""
        self.rep = self._make_rep()
        self.rep.load_state_dict(d["rep"], ctx=ctx)
        self.mean, self.components = np.asarray(d["mean"]), np.asarray(d["components"])
        self.singular_values, self.n_train = np.asarray(d["singular_values"]), int(d["n_train"])
        self._shape, self._channels = tuple(d["shape"]), int(d["channels"])


@hookimpl
def fwk_register_models():
    return [PCA]
