r"""An example third-party sampler: a mesh hierarchy by farthest-point sampling, ``fps`` (the
sampling layer of PointNet++, Qi et al. 2017, "PointNet++: Deep Hierarchical Feature Learning on
Point Sets in a Metric Space", section 3.2, applied to the template's vertices; Euclidean, no
geodesics).

Sampling. Each level keeps a subset of the previous level's vertices. Per connected component
C (components never mix) with vertices x_i, FPS starts at the vertex nearest the component's
centroid, s_1 = argmin_i ||x_i - mean_C x||, and adds the vertex farthest from those chosen,

    s_{t+1} = argmax_{i in C} min_{j <= t} ||x_i - x_{s_j}||        (the lowest index on ties),

until the component keeps m_C = max(ceil(|C| / f), min(|C|, ``min_vertices``)) vertices (f the
level's factor, as ``quadric`` counts them). The kept vertices cover the component evenly: each
new one is as far as possible from the others, so the covering radius roughly halves as m_C
quadruples on a surface. The next level's vertices are the kept ones, in their order on the
finer level (``Level.centres``: their indices there).

Cells. Each fine vertex i belongs to the cell of its nearest kept vertex of its component,
c(i) = argmin_{k kept, same component} ||x_i - x_k|| (a kept vertex is its own cell's centre).

Operators (sparse, nothing n x n is formed):

* ``down`` (n_{l+1} x n_l): ``mean`` (default) averages each cell, D[k, i] = 1 / |cell k| for
  i in cell k (a low-pass before subsampling, like PointNet++'s grouping followed by pooling);
  ``select`` keeps the centre's own value, D[k, s_k] = 1 (CoMA's selection; convs that fuse a
  selecting pooling, ``FusedPoolingConv``, then compute only the kept rows).
* ``up`` (n_l x n_{l+1}): PointNet++'s feature propagation (eq. 2): each fine vertex
  interpolates its ``k`` nearest kept vertices of its component with inverse-distance weights,

      U[i, j] = w_ij / sum_j' w_ij',   w_ij = 1 / ||x_i - x_j||^2,

  and a kept vertex copies its own value (U[s_k, k] = 1), so D U = I with ``select``. Rows of U
  (and of D) sum to 1.

Edges. Level l + 1 has an edge between two kept vertices whose cells are joined by an edge of
level l (the edges contracted onto the cells' centres): the coarse graph is connected where the
fine one is, never joins components, and follows the mesh's own connectivity. The coarse levels
are graphs without triangles (``faces`` None; convs that need faces, the spirals, need another
sampler); ``vertices`` are the template positions of the kept vertices; ``pool`` (on level
l + 1: each kept vertex's cell on level l, centre first) and ``unpool`` (on level l: the up
operator's support of each vertex) are the supports a strided convolution reads.

Euclidean distances ignore the surface: across a narrow gap (lips, eyelids) a cell can take
vertices of the other side, as PointNet++'s balls do. Built once per template and cached
(``fwk.cache.Cache``, keyed by the template's content and the parameters).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from fwk.errors import RecipeError
from fwk.graph import padded_rows
from fwk.hookspecs import hookimpl
from fwk.protocols import Hierarchy, Level, Neighbourhood

#: bumped when a hierarchy built from the same parameters would differ (the cache key)
VERSION = "v1"
DOWNS = ("mean", "select")


def farthest_points(X: np.ndarray, m: int) -> np.ndarray:
    """The indices of m farthest-point samples of X (p, 3), in the order FPS picks them: the
    point nearest the centroid first, then each time the point farthest from those chosen
    (the lowest index on ties)."""
    X = np.asarray(X, dtype=np.float64)
    m = min(int(m), len(X))
    out = np.empty(m, dtype=np.int64)
    if m == 0:
        return out
    out[0] = int(np.argmin(((X - X.mean(axis=0)) ** 2).sum(axis=1)))
    d = ((X - X[out[0]]) ** 2).sum(axis=1)
    for t in range(1, m):
        j = int(np.argmax(d))
        out[t] = j
        np.minimum(d, ((X - X[j]) ** 2).sum(axis=1), out=d)
    return out


def _level_step(V: np.ndarray, E: np.ndarray, labels: np.ndarray, factor: int, min_vertices: int, k: int,
                down: str):
    """One level: (kept (sorted indices), D, U, coarse edges, cell of every fine vertex)."""
    n = len(V)
    kept = []
    for c in np.unique(labels):
        idx = np.flatnonzero(labels == c)
        m = max(int(np.ceil(len(idx) / factor)), min(len(idx), min_vertices))
        kept.append(idx[farthest_points(V[idx], m)])
    kept = np.sort(np.concatenate(kept))
    nc = len(kept)
    pos = np.full(n, -1, dtype=np.int64)
    pos[kept] = np.arange(nc)
    cell = np.empty(n, dtype=np.int64)
    up_rows, up_cols, up_vals = [kept], [np.arange(nc)], [np.ones(nc)]  # a kept vertex copies its own value
    for c in np.unique(labels):
        fine = np.flatnonzero(labels == c)
        ck = kept[labels[kept] == c]  # this component's kept vertices (fine indices)
        kk = min(k, len(ck))
        dist, near = cKDTree(V[ck]).query(V[fine], k=kk)
        dist, near = np.asarray(dist).reshape(len(fine), kk), np.asarray(near).reshape(len(fine), kk)
        cell[fine] = pos[ck[near[:, 0]]]
        w = 1.0 / np.maximum(dist, 1e-150) ** 2
        exact = dist[:, 0] <= 1e-12 * max(float(dist.max(initial=0.0)), 1e-300)
        w[exact] = 0.0
        w[exact, 0] = 1.0  # on a copy of a kept vertex's position: that vertex's value
        w /= w.sum(axis=1, keepdims=True)
        other = pos[fine] < 0
        up_rows.append(np.repeat(fine[other], kk))
        up_cols.append(pos[ck[near[other]]].ravel())
        up_vals.append(w[other].ravel())
    cell[kept] = np.arange(nc)  # a kept vertex is its own cell's centre (also where positions repeat)
    U = sp.csr_matrix((np.concatenate(up_vals), (np.concatenate(up_rows), np.concatenate(up_cols))), shape=(n, nc))
    U.sum_duplicates()
    U.eliminate_zeros()
    if down == "select":
        D = sp.csr_matrix((np.ones(nc), (np.arange(nc), kept)), shape=(nc, n))
    else:
        size = np.bincount(cell, minlength=nc).astype(np.float64)
        D = sp.csr_matrix((1.0 / size[cell], (cell, np.arange(n))), shape=(nc, n))
    Ec = cell[np.asarray(E, dtype=np.int64).reshape(-1, 2)]
    Ec = np.sort(Ec[Ec[:, 0] != Ec[:, 1]], axis=1)
    Ec = np.unique(Ec, axis=0) if len(Ec) else np.zeros((0, 2), dtype=np.int64)
    return kept, D, U, Ec.astype(np.int64), cell


class FarthestPointSampler:
    """Farthest-point sampling hierarchy (PointNet++): FPS vertex subsets, cell-mean down, inverse-distance up.

    Per connected component, each level keeps ceil(n / f) vertices (at least ``min_vertices``)
    chosen by farthest-point sampling, s_{t+1} = argmax_i min_{j <= t} ||x_i - x_{s_j}||; each
    vertex belongs to the cell of its nearest kept vertex. down: the cell mean (``mean``) or
    the kept vertex's own value (``select``); up: the ``k`` nearest kept vertices weighted by
    1 / d^2, normalised (PointNet++ eq. 2); coarse edges: the fine edges contracted onto the
    cells. Levels below the template are graphs (no faces).

    Args:
        factors (list[int] | None): the pooling factor f of each level (None: [4, 4, 4, 4]),
            each at least 2.
        min_vertices (int): the fewest vertices a connected component keeps on a level.
        k (int): kept vertices each vertex interpolates from when up-sampling (PointNet++: 3).
        down (str): ``mean`` (average of the cell) or ``select`` (the kept vertex's value).
    """

    name = "fps"

    def __init__(self, factors: list[int] | None = None, min_vertices: int = 4, k: int = 3,
                 down: Literal["mean", "select"] = "mean"):
        self.factors = [4, 4, 4, 4] if factors is None else list(factors)
        if not self.factors:
            raise RecipeError("factors: at least one level (a list of pooling factors, e.g. [4, 4])")
        for f in self.factors:
            if isinstance(f, bool) or not isinstance(f, int) or f < 2:
                raise RecipeError(f"factors: every pooling factor is an integer >= 2 (1 keeps every vertex), "
                                  f"got {self.factors}")
        if isinstance(min_vertices, bool) or not isinstance(min_vertices, int) or min_vertices < 1:
            raise RecipeError(f"min_vertices: at least 1, got {min_vertices!r}")
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise RecipeError(f"k: at least 1 neighbour to interpolate from, got {k!r}")
        if down not in DOWNS:
            raise RecipeError(f"down: expected one of {', '.join(DOWNS)}, got {down!r}")
        self.min_vertices, self.k, self.down = min_vertices, k, down

    def build(self, template, cache=None) -> Hierarchy:
        def make():
            V = np.asarray(template.vertices, dtype=np.float64)
            E = np.asarray(template.edges, dtype=np.int64)
            labels = np.asarray(template.components, dtype=np.int64)
            levels = [Level(len(V), E, np.asarray(template.triangles, dtype=np.int64), V)]
            downs, ups = [], []
            for i, f in enumerate(self.factors):
                kept, D, U, Ec, cell = _level_step(V, E, labels, f, self.min_vertices, self.k, self.down)
                if len(kept) >= len(V):
                    raise RecipeError(f"factors: level {i + 1} cannot have fewer vertices than level {i} ({len(V)} "
                                      f"vertices in {len(np.unique(labels))} components, at least "
                                      f"{self.min_vertices} kept in each): give fewer factors or a lower "
                                      f"min_vertices")
                fine = levels[-1]
                fine.unpool = Neighbourhood(*padded_rows(U))
                members = sp.csr_matrix((np.ones(len(cell)), (cell, np.arange(len(cell)))), shape=(len(kept), len(V)))
                V, E, labels = V[kept], Ec, labels[kept]
                levels.append(Level(len(kept), E, None, V, pool=Neighbourhood(*padded_rows(members, first=kept)),
                                    centres=kept))
                downs.append(D.tocsr())
                ups.append(U.tocsr())
            return Hierarchy(levels, downs, ups)

        if cache is None:
            return make()
        key = (template.content_hash(), self.factors, self.min_vertices, self.k, self.down, VERSION)
        return cache.get_or_build(self.name, key, make)


@hookimpl
def fwk_register_samplers():
    return [FarthestPointSampler]
