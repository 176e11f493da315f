"""Followers: the parts of a full mesh outside a model's region, moved with the predicted face.

A blendshapes model learns a region: the first n of a full template's n_full vertices (the
rest, e.g. teeth, gums, tongue, eyes, eyelashes, are cut off before training). ``fwk apply`` on
the full mesh predicts the region; the followers move every other vertex the way the training
data moves it, scaled to the predicted face.

Everything below is in the registered frame of the run's preprocessing (``fwk.data.preprocess``:
each subject centred, rotated onto the mean training neutral and scaled by the dataset's s; the
same per-subject transform, computed from the region, is applied to the outside vertices and to
the expressions). D_s,e(v) = X_s,e(v) - X_s,neutral(v) is subject s's registered delta of
expression e at vertex v.

Parts. The vertices v >= n are split into connected components of the outside-only graph (the
template's edges whose two ends are both >= n): each tooth, the gums and tongue, an eyeball, a
row of eyelashes is a part p.

Fitting, on the training subjects only, per expression e and part p:

* G_e(v) = mean over subjects of D_s,e(v) (NaN, a missing shape, left out), for every vertex;
* p does not move for e (nothing is stored) when max_{v in p} |G_e(v)| < ``NEGLIGIBLE`` (1e-3)
  times max_v |G_e(v)| over the whole mesh (region and outside);
* anchors A(p, e): among the region vertices u < n with |G_e(u)| >= ``ANCHOR_MIN`` (0.1) times
  max_{v in p} |G_e(v)|, the ``ANCHORS`` (64) nearest to p (distance to p's nearest vertex, on the
  mean registered training neutral); fewer when fewer qualify, none when none do. G_A is their
  mean delta G_e(A).

Prediction for a new head with registered neutral X (region part X_r) and the model's predicted
registered region delta D (n, 3) of e:

* a = <D(A), G_A> / <G_A, G_A> (the least-squares amplitude of the predicted face near the part
  against the training mean there), clipped to [``A_MIN``, ``A_MAX``] = [0, 3] (0: a part never
  moves against its expression; 3: three times the training mean's motion, beyond any sane
  subject);
* a part without anchors takes a = rho = rms(X_r - mean X_r) / rms(M_r - mean M_r), the head's
  size over the mean training neutral M's (1 for a head of the training mean's size: the
  training mean's delta), so that a scaled head moves its parts scaled;
* the part's registered delta is a G_e(p); the parts not stored for e stay still.

Back in the input frame the delta is R^T (a G) / s with the neutral's own rotation R and the
dataset scale s of the preprocessing (the translation cancels in a delta): a rigid motion of the
input head moves the result rigidly, and a uniformly scaled head (with its prediction scaled
alike) gives the scaled result (a and rho scale with it).

The state is arrays only (``state_dict``, saved by the blendshapes task as
``stats/followers.npz``; read with ``fwk.safeio.load_npz``, never unpickled).
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import DataError

NEGLIGIBLE = 1e-3  # a part moves for e when its largest mean delta is at least this times e's largest
ANCHOR_MIN = 0.1  # an anchor's mean delta is at least this times the part's largest
ANCHORS = 64  # the nearest qualifying region vertices per part and expression
A_MIN, A_MAX = 0.0, 3.0  # the amplitude's clip range


def outside_parts(edges: np.ndarray, n: int, n_full: int) -> np.ndarray:
    """(n_full - n,) int64: the part (connected component of the outside-only graph) of each
    vertex n..n_full-1, numbered by their lowest vertex."""
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    e = e[(e >= n).all(axis=1)] - n
    m = n_full - n
    A = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    _, lab = connected_components(A, directed=False)
    # renumber by first vertex so the numbering does not depend on scipy's
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(np.argsort(first))
    return order[lab].astype(np.int64)


def _size(X: np.ndarray) -> np.ndarray:
    """rms distance of the vertices (..., n, 3) from their centroid."""
    return np.sqrt(((X - X.mean(axis=-2, keepdims=True)) ** 2).sum(-1).mean(-1))


class Followers:
    """The fitted followers of a full mesh (see the module docstring): per stored (expression,
    part) entry the part's mean registered delta G and its anchors with their mean delta G_A."""

    def __init__(self, n: int, parts: np.ndarray, expressions: list[str], entry_expr, entry_part,
                 g_offsets, g, a_offsets, anchors, anchor_g, ref_size: float):
        self.n, self.parts = int(n), np.asarray(parts, dtype=np.int64)
        self.n_full = self.n + len(self.parts)
        self.expressions = [str(e) for e in expressions]
        self.entry_expr = np.asarray(entry_expr, dtype=np.int64)
        self.entry_part = np.asarray(entry_part, dtype=np.int64)
        self.g_offsets, self.g = np.asarray(g_offsets, dtype=np.int64), np.asarray(g, dtype=np.float64)
        self.a_offsets, self.anchors = np.asarray(a_offsets, dtype=np.int64), np.asarray(anchors, dtype=np.int64)
        self.anchor_g = np.asarray(anchor_g, dtype=np.float64)
        self.ref_size = float(ref_size)
        self._members = [np.flatnonzero(self.parts == p) for p in range(int(self.parts.max(initial=-1)) + 1)]
        self._check()

    def _check(self):
        k = len(self.entry_expr)
        ok = (len(self.entry_part) == k and len(self.g_offsets) == len(self.a_offsets) == k + 1
              and self.g_offsets[-1] == len(self.g) and self.a_offsets[-1] == len(self.anchors) == len(self.anchor_g)
              and all(0 <= e < len(self.expressions) for e in self.entry_expr)
              and all(0 <= p < len(self._members) for p in self.entry_part)
              and all(self.g_offsets[i + 1] - self.g_offsets[i] == len(self._members[p])
                      for i, p in enumerate(self.entry_part))
              and (len(self.anchors) == 0 or (self.anchors.min() >= 0 and self.anchors.max() < self.n))
              and self.ref_size > 0)
        if not ok:
            raise DataError("followers: inconsistent arrays (not written by fwk.rig.follow.Followers.state_dict)")

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, edges: np.ndarray, n: int, mean_neutral: np.ndarray, deltas, expressions: list[str]) -> "Followers":
        """Fit on the training subjects: ``mean_neutral`` (n_full, 3) the mean registered training
        neutral, ``deltas`` a mapping (or a callable) expression -> (S, n_full, 3) registered
        deltas of the training subjects (NaN: missing), ``edges`` the full template's edges."""
        M = np.asarray(mean_neutral, dtype=np.float64)
        n_full = len(M)
        if not 0 < n < n_full:
            raise DataError(f"followers: the region has {n} vertices, the full mesh {n_full}: nothing outside")
        parts = outside_parts(edges, n, n_full)
        members = [np.flatnonzero(parts == p) + n for p in range(int(parts.max()) + 1)]
        trees = [cKDTree(M[idx]) for idx in members]
        ex, pa, gs, go, an, ag, ao = [], [], [], [0], [], [], [0]
        for i, e in enumerate(expressions):
            D = np.asarray(deltas(e) if callable(deltas) else deltas[e], dtype=np.float64)
            if D.shape[1:] != (n_full, 3):
                raise DataError(f"followers: {e}'s deltas have shape {D.shape}, expected (subjects, {n_full}, 3)")
            G = np.nanmean(D, axis=0)
            mag = np.linalg.norm(G, axis=1)
            top = float(mag.max()) if len(mag) else 0.0
            for p, idx in enumerate(members):
                peak = float(mag[idx].max())
                if not top > 0 or peak < NEGLIGIBLE * top:
                    continue
                cand = np.flatnonzero(mag[:n] >= ANCHOR_MIN * peak)
                if len(cand):
                    dist, _ = trees[p].query(M[cand])
                    cand = cand[np.argsort(dist, kind="stable")[:ANCHORS]]
                ex.append(i)
                pa.append(p)
                gs.append(G[idx])
                go.append(go[-1] + len(idx))
                an.append(cand)
                ag.append(G[cand])
                ao.append(ao[-1] + len(cand))
        cat = (lambda xs, w: np.concatenate(xs) if xs else np.zeros((0, 3) if w else 0))
        return cls(n, parts, expressions, ex, pa, go, cat(gs, 3), ao, cat(an, 0).astype(np.int64), cat(ag, 3),
                   float(_size(M[:n])))

    # ------------------------------------------------------------------ predicting
    def entries(self, expression: str):
        """(part, G (k, 3), anchors (m,), G_A (m, 3)) of every part that moves for ``expression``."""
        if expression not in self.expressions:
            return
        i = self.expressions.index(expression)
        for k in np.flatnonzero(self.entry_expr == i):
            yield (int(self.entry_part[k]), self.g[self.g_offsets[k]:self.g_offsets[k + 1]],
                   self.anchors[self.a_offsets[k]:self.a_offsets[k + 1]],
                   self.anchor_g[self.a_offsets[k]:self.a_offsets[k + 1]])

    def amplitude(self, D: np.ndarray, anchors: np.ndarray, GA: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """(B,) a = <D(A), G_A> / <G_A, G_A> clipped to [A_MIN, A_MAX]; rho without anchors."""
        if len(anchors) == 0:
            return np.asarray(rho, dtype=np.float64)
        a = np.einsum("bmk,mk->b", D[:, anchors], GA) / float((GA * GA).sum())
        return np.clip(a, A_MIN, A_MAX)

    def deltas(self, X_region: np.ndarray, D_region: np.ndarray, expression: str,
               fixed: float | None = None) -> np.ndarray:
        """(B, n_full - n, 3) registered deltas of the outside vertices for ``expression``, from
        registered region neutrals ``X_region`` (B, n, 3) and predicted registered region deltas
        ``D_region`` (B, n, 3); ``fixed``: every part's a instead (1: the training mean's motion,
        a baseline)."""
        X, D = np.asarray(X_region, dtype=np.float64), np.asarray(D_region, dtype=np.float64)
        if X.ndim == 2:
            return self.deltas(X[None], D[None], expression, fixed)[0]
        if X.shape[1:] != (self.n, 3) or D.shape != X.shape:
            raise DataError(f"followers: region of shape {X.shape[1:]} / {D.shape[1:]}, expected ({self.n}, 3)")
        rho = _size(X) / self.ref_size
        out = np.zeros((len(X), self.n_full - self.n, 3))
        for p, G, A, GA in self.entries(expression):
            a = self.amplitude(D, A, GA, rho) if fixed is None else np.full(len(X), float(fixed))
            out[:, self._members[p]] = a[:, None, None] * G[None]
        return out

    def summary(self) -> dict:
        """{expression: number of parts that move} (expressions moving none left out)."""
        out = {}
        for i in self.entry_expr:
            out[self.expressions[i]] = out.get(self.expressions[i], 0) + 1
        return out

    # ------------------------------------------------------------------ saving
    def state_dict(self) -> dict:
        """Arrays only (saved as ``stats/followers.npz``)."""
        return {"n": np.int64(self.n), "parts": self.parts, "expressions": np.array(self.expressions, dtype=str),
                "entry_expr": self.entry_expr, "entry_part": self.entry_part, "g_offsets": self.g_offsets,
                "g": self.g, "a_offsets": self.a_offsets, "anchors": self.anchors, "anchor_g": self.anchor_g,
                "ref_size": np.float64(self.ref_size)}

    @classmethod
    def from_state(cls, d, source: str = "followers") -> "Followers":
        """Restored from ``state_dict``'s arrays; a DataError naming ``source`` when they are not."""
        try:
            return cls(int(d["n"]), d["parts"], list(np.asarray(d["expressions"]).tolist()), d["entry_expr"],
                       d["entry_part"], d["g_offsets"], d["g"], d["a_offsets"], d["anchors"], d["anchor_g"],
                       float(d["ref_size"]))
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            raise DataError(f"{source}: not the followers of a blendshapes run ({type(exc).__name__}: "
                            f"{str(exc)[:120]})") from None
        except DataError as exc:
            raise DataError(f"{source}: {exc}") from None


def follow(pre, followers: Followers, V_full: np.ndarray, shapes: dict) -> dict:
    """The full head's expressions: ``V_full`` (n_full, 3) a neutral in the run's units and place,
    ``shapes`` {expression: (n, 3)} the model's predicted region in the same frame; returns
    {expression: (n_full, 3)}: the region as predicted, the outside moved by the followers (their
    registered deltas mapped back with the neutral's own registration ``pre``:
    ``fwk.data.preprocess.Preprocessor``; R^T d / s)."""
    V = np.asarray(V_full, dtype=np.float64)
    n = followers.n
    X, T = pre.transform_neutrals(V[:n])
    out = {}
    for e, P in shapes.items():
        P = np.asarray(P, dtype=np.float64)
        D = pre.apply(P[None], T)[0] - X
        d = followers.deltas(X, D, e)
        full = V.copy()
        full[:n] = P
        full[n:] += (T.rotation[0].T @ d.T).T / T.scale
        out[e] = full
    return out
