"""Sampler ``simple``: the connectivity-only graph sampling of the fully convolutional mesh
autoencoder (Zhou et al. 2020, "Fully Convolutional Mesh Autoencoder using Efficient
Spatially Varying Kernels"; thesis 3.3, appendix A).

On each level's graph (``stride`` and ``radius`` may be lists, one entry per level, the last
repeating), per connected component: walk the vertices in breadth-first order from
the component's first vertex; a vertex not yet covered becomes a centre and covers every vertex
within ``stride - 1`` hops. Centres are therefore at least ``stride`` hops apart and every vertex
lies within ``stride - 1`` hops of a centre. The next level's vertices are the centres; two
centres are joined when they are at most ``2 stride - 1`` hops apart (their covering balls touch
or overlap), which gives non-manifold graphs, as in the paper.

Neighbourhoods, stored in the typed fields of ``fwk.protocols.Level`` as
``Neighbourhood(index, mask)`` (padded index arrays with boolean masks):

* ``conv`` on every level: the vertices within ``radius`` hops of each vertex (itself first):
  the support of a stride-1 convolution;
* ``pool`` on level i + 1: for each centre, the level-i vertices within ``radius`` hops (centre
  first; a strided convolution's support, and ``down``: their mean); ``centres`` on level
  i + 1: the centres' indices on level i;
* ``unpool`` on level i: for each level-i vertex, the centres whose pool neighbourhood contains
  it (a transposed convolution's support, and ``up``: their mean).

``down`` and ``up`` are sparse averaging operators (rows sum to 1). Several connected components
are handled, each keeping at least one centre; nothing n x n is dense.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from fwk.errors import RecipeError
from fwk.graph import adjacency, padded_rows, reach
from fwk.hookspecs import hookimpl
from fwk.protocols import Hierarchy, Level, Neighbourhood


_adj, _within, _padded = adjacency, reach, padded_rows


def _mean_op(R):
    R = R.tocsr().astype(np.float64)
    R.data[:] = 1.0
    d = np.asarray(R.sum(1)).ravel()
    return sp.diags(1.0 / np.maximum(d, 1)) @ R


def centres_bfs(A, stride):
    n = A.shape[0]
    _, labels = connected_components(A, directed=False)
    covered = np.zeros(n, bool)
    cover = _within(A, stride - 1)
    centres = []
    for c in range(labels.max() + 1):
        start = int(np.flatnonzero(labels == c)[0])
        order = breadth_first_order(A, start, directed=False, return_predecessors=False)
        for v in order:
            if not covered[v]:
                centres.append(int(v))
                covered[cover.indices[cover.indptr[v]:cover.indptr[v + 1]]] = True
    return np.array(sorted(centres), dtype=np.int64)


class Simple:
    """Connectivity-only sampling (Zhou et al. 2020): BFS centres with a stride, radius neighbourhoods."""

    name = "simple"

    def __init__(self, levels: int = 4, stride: int | list[int] = 2, radius: int | list[int] = 2):
        if levels < 1:
            raise RecipeError(f"levels: at least 1, got {levels}")
        strides = list(stride) if isinstance(stride, (list, tuple)) else [stride]
        radii = list(radius) if isinstance(radius, (list, tuple)) else [radius]
        if not strides or not radii:
            raise RecipeError("stride/radius: give a number or a non-empty list (one entry per level)")
        self.strides = [strides[min(i, len(strides) - 1)] for i in range(levels)]
        self.radii = [radii[min(i, len(radii) - 1)] for i in range(levels)]
        for i, (st, r) in enumerate(zip(self.strides, self.radii)):
            if st < 2:
                raise RecipeError(f"stride: at least 2 (a stride of 1 keeps every vertex), got {st} at level {i}")
            if r < st - 1:
                raise RecipeError(f"radius: at least stride - 1 = {st - 1} so every vertex is pooled, got {r} at level {i}")
        self.n_levels = levels

    def build(self, template, cache=None) -> Hierarchy:
        def make():
            n = template.n_vertices
            A = _adj(template.edges, n)
            V = np.asarray(template.vertices, dtype=np.float64)
            levels = [Level(n, np.asarray(template.edges), np.asarray(template.triangles), V)]
            downs, ups = [], []
            for stride, radius in zip(self.strides, self.radii):
                C = centres_bfs(A, stride)
                conv = _within(A, radius)
                P = conv[C]  # (n_c, n): pool neighbourhoods
                D = _mean_op(P)
                U = _mean_op(P.T)
                reach = _within(A, 2 * stride - 1)[C][:, C].tocoo()
                keep = reach.row < reach.col
                E = np.stack([reach.row[keep], reach.col[keep]], 1)
                lv = levels[-1]
                lv.conv = Neighbourhood(*_padded(conv, first=np.arange(A.shape[0])))
                lv.unpool = Neighbourhood(*_padded(P.T.tocsr()))
                nxt = Level(len(C), E, None, V[C], pool=Neighbourhood(*_padded(P, first=C)), centres=C)
                downs.append(D.tocsr())
                ups.append(U.tocsr())
                levels.append(nxt)
                A, V = _adj(E, len(C)), V[C]
            last = levels[-1]
            last.conv = Neighbourhood(*_padded(_within(A, self.radii[-1]), first=np.arange(A.shape[0])))
            return Hierarchy(levels, downs, ups)

        if cache is None:
            return make()
        # "v3": Levels carry typed neighbourhoods (was an untyped ``extra`` dict): older entries rebuild
        key = (template.content_hash(), self.n_levels, self.strides, self.radii, "v3")
        return cache.get_or_build(self.name, key, make)


@hookimpl
def fwk_register_samplers():
    return [Simple]
