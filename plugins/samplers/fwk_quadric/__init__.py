"""Sampler ``quadric``: the mesh hierarchy of CoMA (Ranjan et al. 2018), used by Neural 3DMM,
SpiralNet++, FeaStNet and LSA-3DMM autoencoders (thesis 3.3, appendix A).

Each level keeps a subset of the previous level's vertices, chosen by quadric-error edge
collapses (Garland & Heckbert 1997) in which an edge (u, v) collapses onto one of its endpoints
(the one with the lower error v^T (Q_u + Q_v) v, Q the sum of the plane quadrics of the incident
faces), until each connected component has 1/factor of its vertices (at least ``min_vertices``).
Border edges add a heavily weighted plane perpendicular to their face (Garland & Heckbert's
boundary constraint), so open meshes (a face region) keep their outline instead of shrinking.
A collapse that would break the link condition (more than two common neighbours) is skipped,
so the coarse mesh stays manifold where the input was.

* down (n_{i+1} x n_i): selection of the kept vertices (exact correspondence);
* up (n_i x n_{i+1}): each fine vertex's barycentric coordinates on the closest coarse
  triangle *of its own component* (the weights sum to 1 also when the closest point lies on an
  edge or a corner; the reference code solves against the raw vertex there and its weights
  need not sum to 1). Both are sparse; nothing n x n is formed.

Meshes with several connected components are handled (every component is simplified on its
own quota and keeps at least ``min_vertices``), which the reference implementations do not.
"""
from __future__ import annotations

import heapq

import numpy as np
import scipy.sparse as sp

from fwk.errors import RecipeError
from fwk.geometry import connected_components
from fwk.hookspecs import hookimpl
from fwk.protocols import Hierarchy, Level


def _plane_quadrics(V, F, border_weight: float = 100.0):
    """Per-vertex sums of the plane quadrics p p^T of the incident faces, plus, for every border
    edge, ``border_weight`` times the quadric of the plane through the edge perpendicular to its
    face (Garland & Heckbert 1997, section 6.1), so that borders keep their shape."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.maximum(area, 1e-300)
    p = np.hstack([n, -np.einsum("ij,ij->i", n, V[F[:, 0]])[:, None]])  # (m, 4)
    K = p[:, :, None] * p[:, None, :]
    Q = np.zeros((len(V), 4, 4))
    for k in range(3):
        np.add.at(Q, F[:, k], K)
    # border edges: directed edges whose twin is missing
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    fid = np.tile(np.arange(len(F)), 3)
    key = he[:, 0].astype(np.int64) * len(V) + he[:, 1]
    twin = he[:, 1].astype(np.int64) * len(V) + he[:, 0]
    border = ~np.isin(twin, key)
    if border_weight > 0 and border.any():
        a, b, f = he[border, 0], he[border, 1], fid[border]
        m = np.cross(V[b] - V[a], n[f])
        m = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
        q = np.hstack([m, -np.einsum("ij,ij->i", m, V[a])[:, None]])
        Kb = border_weight * q[:, :, None] * q[:, None, :]
        np.add.at(Q, a, Kb)
        np.add.at(Q, b, Kb)
    return Q


def simplify(V: np.ndarray, F: np.ndarray, factor: float, min_vertices: int = 4):
    """(kept vertex indices (sorted), coarse faces in kept indices) by endpoint edge collapses."""
    n = len(V)
    labels = connected_components(F, n)
    comp_n = np.bincount(labels)
    target = np.maximum(np.ceil(comp_n / factor).astype(int), np.minimum(comp_n, min_vertices))
    alive_count = comp_n.copy()
    Q = _plane_quadrics(V, F)
    Vh = np.hstack([V, np.ones((n, 1))])
    nbr = [set() for _ in range(n)]
    faces = {i: tuple(map(int, f)) for i, f in enumerate(F)}
    vfaces = [set() for _ in range(n)]
    for i, f in faces.items():
        for a in f:
            vfaces[a].add(i)
            nbr[a].update(x for x in f if x != a)
    alive = np.ones(n, bool)
    version = np.zeros(n, dtype=np.int64)

    def cost(u, v):
        q = Q[u] + Q[v]
        cu = float(Vh[u] @ q @ Vh[u])
        cv = float(Vh[v] @ q @ Vh[v])
        return (cu, u, v) if cu <= cv else (cv, v, u)  # (error, keep, remove)

    # initial costs of every edge, vectorised; then one heapify
    E = _edges(np.asarray(F, dtype=np.int64)).reshape(-1, 2)
    q = Q[E[:, 0]] + Q[E[:, 1]]
    cu = np.einsum("ei,eij,ej->e", Vh[E[:, 0]], q, Vh[E[:, 0]])
    cv = np.einsum("ei,eij,ej->e", Vh[E[:, 1]], q, Vh[E[:, 1]])
    first = cu <= cv
    keep0 = np.where(first, E[:, 0], E[:, 1])
    rem0 = np.where(first, E[:, 1], E[:, 0])
    heap = list(zip(np.where(first, cu, cv).tolist(), keep0.tolist(), rem0.tolist(), [0] * len(E), [0] * len(E)))
    heapq.heapify(heap)
    while heap:
        c, keep, rem, vk, vr = heapq.heappop(heap)
        if not (alive[keep] and alive[rem]) or version[keep] != vk or version[rem] != vr:
            continue
        lab = labels[rem]
        if alive_count[lab] <= target[lab]:
            continue
        if len(nbr[keep] & nbr[rem]) > 2:  # link condition
            continue
        # collapse rem -> keep
        for fi in list(vfaces[rem]):
            f = faces[fi]
            if keep in f:
                for a in f:
                    vfaces[a].discard(fi)
                del faces[fi]
            else:
                nf = tuple(keep if a == rem else a for a in f)
                faces[fi] = nf
                vfaces[keep].add(fi)
        for w in nbr[rem]:
            nbr[w].discard(rem)
            if w != keep:
                nbr[w].add(keep)
                nbr[keep].add(w)
        nbr[keep].discard(rem)
        nbr[rem] = set()
        vfaces[rem] = set()
        alive[rem] = False
        alive_count[lab] -= 1
        Q[keep] += Q[rem]
        version[keep] += 1
        for w in nbr[keep]:
            c2, k2, r2 = cost(keep, w)
            heapq.heappush(heap, (c2, k2, r2, version[k2], version[r2]))
    kept = np.flatnonzero(alive)
    remap = -np.ones(n, dtype=np.int64)
    remap[kept] = np.arange(len(kept))
    Fc = np.array([[remap[a] for a in f] for f in faces.values()], dtype=np.int64).reshape(-1, 3)
    return kept, Fc


def closest_on_triangles(P, A, B, C):
    """Barycentric coordinates (k, 3) of the closest points to P (k, 3) on triangles ABC
    (Ericson, Real-Time Collision Detection 5.1.5), vectorised; squared distances (k,)."""
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = P - B
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = P - C
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    w = np.zeros((len(P), 3))
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v_in = vb / denom
        w_in = vc / denom
        w[:] = np.stack([1 - v_in - w_in, v_in, w_in], -1)  # inside the face
        # edge regions
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    w[on_bc] = np.stack([np.zeros(on_bc.sum()), 1 - t_bc[on_bc], t_bc[on_bc]], -1)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    w[on_ac] = np.stack([1 - t_ac[on_ac], np.zeros(on_ac.sum()), t_ac[on_ac]], -1)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    w[on_ab] = np.stack([1 - t_ab[on_ab], t_ab[on_ab], np.zeros(on_ab.sum())], -1)
    # vertex regions
    at_c = (d6 >= 0) & (d5 <= d6)
    at_b = (d3 >= 0) & (d4 <= d3)
    at_a = (d1 <= 0) & (d2 <= 0)
    for mask, k in ((at_c, 2), (at_b, 1), (at_a, 0)):
        w[mask] = np.eye(3)[k]
    w = np.nan_to_num(w, nan=1.0 / 3)
    Q = w[:, :1] * A + w[:, 1:2] * B + w[:, 2:] * C
    return w, ((P - Q) ** 2).sum(-1)


def barycentric_up(Vf, labels_f, Vc, Fc, labels_c, n_near: int = 8) -> sp.csr_matrix:
    """(n_f x n_c): each fine vertex as barycentric weights of its closest point on the coarse
    triangles *of its own component* (candidates: the triangles around its ``n_near`` nearest
    coarse vertices). Weights are >= 0 and sum to 1 on faces, edges and corners alike."""
    from scipy.spatial import cKDTree

    rows, cols, vals = [], [], []
    for lab in np.unique(labels_f):
        fi = np.flatnonzero(labels_f == lab)
        ci = np.flatnonzero(labels_c == lab)
        tri = Fc[labels_c[Fc[:, 0]] == lab]
        k = min(n_near, len(ci))
        _, near = cKDTree(Vc[ci]).query(Vf[fi], k=k)
        near = ci[np.asarray(near).reshape(len(fi), k)]
        if len(tri) == 0:
            rows += list(fi)
            cols += list(near[:, 0])
            vals += [1.0] * len(fi)
            continue
        vt = sp.csr_matrix((np.ones(3 * len(tri)), (tri.ravel(), np.repeat(np.arange(len(tri)), 3))),
                           shape=(len(Vc), len(tri)))
        best_w = np.zeros((len(fi), 3))
        best_t = np.zeros(len(fi), dtype=np.int64)
        best_d = np.full(len(fi), np.inf)
        for j in range(k):
            # every triangle around the j-th nearest coarse vertex
            sub = vt[near[:, j]]
            r, t = sub.nonzero()
            A, B, C = Vc[tri[t, 0]], Vc[tri[t, 1]], Vc[tri[t, 2]]
            w, d = closest_on_triangles(Vf[fi][r], A, B, C)
            # keep the best per row (several candidates per row in one pass)
            order = np.lexsort((d, r))
            first = np.ones(len(order), bool)
            first[1:] = r[order][1:] != r[order][:-1]
            sel = order[first]
            upd = d[sel] < best_d[r[sel]]
            rr = r[sel][upd]
            best_d[rr], best_w[rr], best_t[rr] = d[sel][upd], w[sel][upd], t[sel][upd]
        rows += list(np.repeat(fi, 3))
        cols += list(tri[best_t].ravel())
        vals += list(best_w.ravel())
    U = sp.coo_matrix((vals, (rows, cols)), shape=(len(Vf), len(Vc))).tocsr()
    U.sum_duplicates()
    U.eliminate_zeros()
    return U


class Quadric:
    """Quadric-error simplification hierarchy (CoMA): vertex-subset down, barycentric up."""

    name = "quadric"

    def __init__(self, factors: list[int] | None = None, min_vertices: int = 4):
        self.factors = list(factors) if factors else [4, 4, 4, 4]
        if any(f < 1 for f in self.factors):
            raise RecipeError(f"factors: pooling factors must be >= 1, got {self.factors}")
        self.min_vertices = min_vertices

    def build(self, template, cache=None) -> Hierarchy:
        def make():
            V = np.asarray(template.vertices, dtype=np.float64)
            F = np.asarray(template.triangles, dtype=np.int64)
            levels = [Level(len(V), _edges(F), F, V)]
            downs, ups = [], []
            for f in self.factors:
                kept, Fc = simplify(V, F, f, self.min_vertices)
                Vc = V[kept]
                D = sp.csr_matrix((np.ones(len(kept)), (np.arange(len(kept)), kept)), shape=(len(kept), len(V)))
                lf = connected_components(F, len(V))
                U = barycentric_up(V, lf, Vc, Fc, lf[kept])
                downs.append(D)
                ups.append(U)
                V, F = Vc, Fc
                levels.append(Level(len(V), _edges(F), F, V))
            return Hierarchy(levels, downs, ups)

        if cache is None:
            return make()
        # "v3": the Level class lost its untyped ``extra`` dict; older pickled entries rebuild
        return cache.get_or_build(self.name, (template.content_hash(), self.factors, self.min_vertices, "v3"), make)


def _edges(F):
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), dtype=np.int64)


@hookimpl
def fwk_register_samplers():
    return [Quadric]
