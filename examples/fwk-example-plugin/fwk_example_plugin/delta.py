r"""An example third-party representation: Laplacian (differential) coordinates, ``delta``
(Sorkine et al. 2004, "Laplacian Surface Editing"; Lipman et al. 2004, "Differential
Coordinates for Interactive Mesh Editing").

Encoding. Each vertex is described by its offset from the centroid of its one-ring,

    delta_i = p_i - (1 / d_i) sum_{j in N(i)} p_j,      i.e.   Delta = L P,   L = I - D^{-1} A,

with A the 0/1 adjacency of the template's edges and D = diag(d_i) the degrees: the uniform
("umbrella") Laplacian of Sorkine et al. The uniform weights are chosen over the cotangent ones
because they depend on the connectivity only: L is the same for every template position (the
fitted mean included), no triangle shape can make a weight negative or unbounded (cotangent
weights of obtuse or needle triangles are, and scans have them), and rows are exactly
translation-invariant (L 1 = 0). A vertex without an edge keeps its position (L_ii = 1, delta_i
= p_i). delta is linear in P and rotation-covariant: it encodes a mesh's local shape (each
one-ring's mean-curvature-like offset) and loses exactly one translation per connected component
(the null space of L is the constants on each component).

Decoding. Features delta (any (n, 3), not necessarily in the range of L: a network's output)
are integrated by the anchored least squares of Sorkine et al. / Lipman et al.:

    X = argmin_X || L X - delta ||^2 + w^2 sum_{a in anchors} || x_a - c_a ||^2,

i.e. the sparse system [L; w S] X = [delta; w S C] (S selects the anchor vertices) solved by its
normal equations (L^T L + w^2 S^T S) X = L^T delta + w^2 S^T C, factorised once per fitted
template (SuperLU) and reused for every mesh and coordinate. The anchors are ``anchors``
vertices per connected component of the fitted mean (the one nearest the component's centroid,
then farthest-point samples), held at the reference C (the fitted training mean; with
``relative: true`` the reference ``ref``). With one anchor per component (the default) the anchor
constraints are met exactly whatever w, so decode(encode(P)) = P + t_c, a translation of each
component that puts its anchor on the reference: the translation delta does not carry. More
anchors hold the low frequencies (the drift an inexact delta integrates into) at the reference
with weight w, at the price of no longer reproducing a mesh whose anchors differ from it.

Placement. As the representation loses translation (``places_rigidly = True``, like ``dr``),
``decode(F, ref, target)`` with the ground truth ``target`` translates each connected component
so that its centroid is the target's (the least-squares translation): the round trip is exact
up to rounding (float64 deltas of 6,000-vertex heads come back to 3e-10 of their size) and an
evaluation scores shape, not the lost placement (as the thesis scores ``dr``); without a target
(``fwk sample``) the anchors place the mesh.

``relative: true`` takes the features against a reference R (``ref``, per sample (b, n, 3) or
shared (n, 3), or the fitted mean): F = g(L (P - R)), decoded as R + X(g^{-1}(F)) with the
anchors held at R (a subject's own neutral for personalised blendshapes). Scaling g is
``fwk.scaling.Scaler`` (none / std / norm, ``granularity``, ``a``, ``eps``), fitted on the
training deltas; ``unscale`` is its differentiable inverse (the loss space).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from fwk.cache import content_key, memo
from fwk.errors import DataError, RecipeError
from fwk.graph import adjacency
from fwk.hookspecs import hookimpl
from fwk.scaling import Scaler


def uniform_laplacian(edges: np.ndarray, n: int) -> sp.csr_matrix:
    """L = I - D^{-1} A of an undirected edge list, (n, n) CSR; a vertex without an edge has the
    row e_i (L_ii = 1)."""
    A = adjacency(np.asarray(edges, dtype=np.int64).reshape(-1, 2), n)
    d = np.asarray(A.sum(axis=1)).ravel()
    inv = np.where(d > 0, 1.0 / np.maximum(d, 1.0), 0.0)
    return (sp.identity(n, format="csr") - sp.diags(inv) @ A).tocsr()


def choose_anchors(V: np.ndarray, labels: np.ndarray, per_component: int) -> np.ndarray:
    """Sorted anchor vertices: per connected component (``labels``), the vertex nearest its
    centroid, then farthest-point samples of V up to ``per_component`` (all of a smaller one)."""
    out = []
    for c in range(int(labels.max()) + 1 if len(labels) else 0):
        idx = np.flatnonzero(labels == c)
        X = V[idx]
        first = int(np.argmin(((X - X.mean(axis=0)) ** 2).sum(axis=1)))
        chosen = [first]
        d = ((X - X[first]) ** 2).sum(axis=1)
        for _ in range(min(per_component, len(idx)) - 1):
            j = int(np.argmax(d))
            chosen.append(j)
            d = np.minimum(d, ((X - X[j]) ** 2).sum(axis=1))
        out.extend(idx[chosen].tolist())
    return np.array(sorted(out), dtype=np.int64)


def _operators(edges: np.ndarray, n: int, anchors: np.ndarray, weight: float) -> dict:
    """L, its transpose, the anchor selection and the factorised normal matrix
    L^T L + w^2 S^T S (SuperLU), and each vertex's connected component."""
    L = uniform_laplacian(edges, n)
    S = sp.csr_matrix((np.ones(len(anchors)), (np.arange(len(anchors)), anchors)), shape=(len(anchors), n))
    Lt = L.T.tocsr()
    N = (Lt @ L + (weight * weight) * (S.T @ S)).tocsc()
    _, labels = connected_components(adjacency(np.asarray(edges, dtype=np.int64).reshape(-1, 2), n), directed=False)
    G = sp.csr_matrix((np.ones(n), (labels, np.arange(n))), shape=(int(labels.max()) + 1, n))
    return {"L": L, "Lt": Lt, "lu": splu(N, permc_spec="COLAMD"), "labels": labels, "G": G,
            "sizes": np.bincount(labels).astype(np.float64)}


def _apply(M, X: np.ndarray) -> np.ndarray:
    """A sparse (m, n) operator on every mesh of a (b, n, c) batch at once: (b, m, c)."""
    b, n, c = X.shape
    return np.asarray(M @ X.transpose(1, 0, 2).reshape(n, b * c)).reshape(M.shape[0], b, c).transpose(1, 0, 2)


class Delta:
    r"""Laplacian coordinates delta = L P (Sorkine et al. 2004), decoded by anchored least squares (3 channels).

    With L = I - D^{-1} A the uniform Laplacian of the template's edges:

        encode:  F = g(L (P - R))
        decode:  X = argmin_X ||L (X - R) - g^{-1}(F)||^2 + w^2 sum_a ||x_a - c_a||^2

    R = 0 and c = the fitted mean, or with ``relative: true`` R = c = the reference ``ref`` (or
    the fitted mean); the anchors a are ``anchors`` vertices per connected component of the
    fitted mean; g is ``fwk.scaling.Scaler``. Decoding with
    a ``target`` translates each connected component onto the target's centroid (delta loses
    translation: ``places_rigidly``).

    Args:
        scaling (str): ``none``, ``std`` (per vertex and channel by default) or ``norm``.
        granularity (str | None): ``vertex`` or ``channel`` statistics (None: the scaling's default).
        a (float): ``norm``'s range [-a, a].
        relative (bool): features against the reference ``ref`` (or the fitted mean).
        eps (float): floor of the standard deviations / ranges.
        anchors (int): anchor vertices per connected component (1: exact round trip up to translation).
        anchor_weight (float): w, how firmly the anchors hold (matters with more than one anchor).
    """

    name = "delta"
    channels = 3
    places_rigidly = True   # delta loses each component's translation: decode places onto `target`
    relative_option = True  # `relative: true` takes delta of P - ref (anchors held at ref)
    relative = False        # the constructor's `relative` sets it per instance
    scaler: Scaler | None = None  # each instance sets its own: the scaling encode applies last

    def __init__(self, scaling: str = "std", granularity: str | None = None, a: float = 1.0,
                 relative: bool = False, eps: float = 1e-8, anchors: int = 1, anchor_weight: float = 1.0):
        if isinstance(anchors, bool) or not isinstance(anchors, int) or anchors < 1:
            raise RecipeError(f"anchors: at least 1 anchor vertex per connected component, got {anchors!r}")
        if isinstance(anchor_weight, bool) or not isinstance(anchor_weight, (int, float)) or \
                not np.isfinite(anchor_weight) or anchor_weight <= 0:
            raise RecipeError(f"anchor_weight: a number > 0, got {anchor_weight!r}")
        if not isinstance(relative, bool):
            raise RecipeError(f"relative: expected true or false, got {relative!r}")
        self.scaler = Scaler(scaling, granularity, a, eps)
        self.relative = relative
        self.anchors, self.anchor_weight = anchors, float(anchor_weight)
        self.mean = self.edges = self.anchor_index = None
        self._ops = None

    # ------------------------------------------------------------------ operators
    def _setup(self, mean: np.ndarray, edges: np.ndarray, anchor_index: np.ndarray | None = None) -> None:
        self.mean = np.asarray(mean, dtype=np.float64)
        self.edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        n = len(self.mean)
        if anchor_index is None:
            _, labels = connected_components(adjacency(self.edges, n), directed=False)
            anchor_index = choose_anchors(self.mean, labels, self.anchors)
        self.anchor_index = np.asarray(anchor_index, dtype=np.int64)
        key = content_key(self.edges, n, self.anchor_index, self.anchor_weight)
        self._ops = memo(f"{__name__}.operators", key,
                         lambda: _operators(self.edges, n, self.anchor_index, self.anchor_weight), size=8)

    def _check(self, X: np.ndarray, what: str) -> np.ndarray:
        if self._ops is None:
            raise RuntimeError("delta representation used before fit() or load_state_dict()")
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 3 or X.shape[1:] != (len(self.mean), 3):
            raise DataError(f"delta.{what}: expected (b, {len(self.mean)}, 3), got {X.shape}")
        return X

    def _ref(self, ref, b: int) -> np.ndarray | None:
        """The reference R (b, n, 3) features are taken against, or None (absolute)."""
        if not self.relative:
            return None
        R = self.mean if ref is None else np.asarray(ref, dtype=np.float64)
        return np.broadcast_to(R, (b, *self.mean.shape))

    def raw_features(self, P, ref=None) -> np.ndarray:
        """(b, n, 3) unscaled delta = L (P - R)."""
        P = self._check(P, "encode")
        R = self._ref(ref, len(P))
        return _apply(self._ops["L"], P if R is None else P - R)

    def integrate(self, delta, ref=None, target=None) -> np.ndarray:
        """(b, n, 3) positions whose Laplacian best matches ``delta`` (b, n, 3) with the anchors
        held at the reference, then translated per component onto ``target`` when given."""
        delta = self._check(delta, "decode")
        b = len(delta)
        o = self._ops
        R = self._ref(ref, b)
        a = self.anchor_index
        w2 = self.anchor_weight ** 2
        rhs = _apply(o["Lt"], delta)
        if R is None:  # absolute: the anchors held at the fitted mean
            rhs[:, a] += w2 * self.mean[a]
        n = len(self.mean)
        X = o["lu"].solve(rhs.transpose(1, 0, 2).reshape(n, b * 3)).reshape(n, b, 3).transpose(1, 0, 2)
        if R is not None:  # relative: X is the offset from R, its anchors held at 0
            X = X + R
        if target is not None:
            T = np.asarray(target, dtype=np.float64).reshape(X.shape)
            shift = _apply(o["G"], T - X) / o["sizes"][None, :, None]  # (b, components, 3) mean offsets
            X = X + shift[:, o["labels"]]
        return X

    # ------------------------------------------------------------------ protocol
    def fit(self, P, ref=None, template=None) -> None:
        P = np.asarray(P, dtype=np.float64)
        if template is None or P.ndim != 3 or P.shape[1:] != (template.n_vertices, 3) or not len(P):
            n = "n" if template is None else template.n_vertices
            raise DataError(f"delta.fit: expected meshes of shape (b, {n}, 3) with b > 0 and their template, "
                            f"got {P.shape}")
        self._setup(P.mean(axis=0), template.edges)
        self.scaler.fit(self.raw_features(P, ref))

    def encode(self, P, ref=None) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64)
        if P.ndim == 2:  # one mesh
            return self.encode(P[None], ref)[0]
        return self.scaler.transform(self.raw_features(P, ref)).astype(np.float32)

    def decode(self, F, ref=None, target=None) -> np.ndarray:
        F = np.asarray(F, dtype=np.float64)
        if F.ndim == 2:  # one mesh
            return self.decode(F[None], ref, None if target is None else np.asarray(target)[None])[0]
        return self.integrate(self.scaler.inverse(F), ref, target)

    def unscale(self, F):
        return self.scaler.inverse_torch(F)

    def state_dict(self) -> dict:
        return {"scaler": self.scaler.state_dict(), "mean": self.mean, "edges": self.edges,
                "anchor_index": self.anchor_index, "relative": self.relative, "anchors": self.anchors,
                "anchor_weight": self.anchor_weight}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        self.scaler.load_state_dict(d["scaler"])
        self.relative = bool(d["relative"])
        self.anchors, self.anchor_weight = int(d["anchors"]), float(d["anchor_weight"])
        self._setup(np.asarray(d["mean"]), np.asarray(d["edges"]), np.asarray(d["anchor_index"]))


@hookimpl
def fwk_register_representations():
    return [Delta]
