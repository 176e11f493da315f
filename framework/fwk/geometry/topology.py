"""Edge structures of a triangle mesh: unique edges, edge-face adjacency, border / interior /
non-manifold classification, vertex-edge incidence. Cached per topology (triangles)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _components

from ..cache import memo
from ..graph import symmetric_adjacency

@dataclass
class EdgeTopology:
    """The edge structures of one triangle list (see the fields); built and cached by
    ``edge_topology``."""

    n_vertices: int
    edges: np.ndarray            # (e, 2) unique undirected edges, i < j
    face_edges: np.ndarray       # (m, 3) edge index of the edge opposite corner k of each face
    edge_count: np.ndarray       # (e,) number of faces using each edge
    interior: np.ndarray         # (e_i,) indices of manifold interior edges (exactly two faces, consistently oriented)
    f1: np.ndarray               # (e_i,) first face of each interior edge (the edge runs a -> b in it)
    f2: np.ndarray               # (e_i,) second face
    a: np.ndarray                # (e_i,) edge start vertex as oriented in f1
    b: np.ndarray                # (e_i,) edge end vertex
    border_vertex: np.ndarray    # (n,) bool: on a border edge
    vertex_edge: sp.csr_matrix   # (n, e_i) incidence of interior edges on vertices

    @property
    def border(self) -> np.ndarray:
        """Indices of the border edges (one face)."""
        return np.flatnonzero(self.edge_count == 1)

    @property
    def non_manifold(self) -> np.ndarray:
        """Indices of the non-manifold edges (more than two faces)."""
        return np.flatnonzero(self.edge_count > 2)


def edge_topology(F: np.ndarray, n_vertices: int | None = None) -> EdgeTopology:
    """The EdgeTopology of triangles F (m, 3) on ``n_vertices`` vertices (default: F.max() + 1),
    cached per topology."""
    F = np.ascontiguousarray(F, dtype=np.int64)
    n = int(n_vertices if n_vertices is not None else F.max() + 1)

    def build():
        m = len(F)
        # directed half-edges opposite corner k: (F[:, k+1], F[:, k+2])
        he_a = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
        he_b = np.concatenate([F[:, 2], F[:, 0], F[:, 1]])
        he_f = np.tile(np.arange(m), 3)
        lo, hi = np.minimum(he_a, he_b), np.maximum(he_a, he_b)
        keys = lo * n + hi
        uniq, inv, count = np.unique(keys, return_inverse=True, return_counts=True)
        edges = np.stack([uniq // n, uniq % n], axis=1)
        face_edges = inv.reshape(3, m).T.copy()
        # interior manifold edges: two half-edges, opposite directions
        order = np.argsort(inv, kind="stable")
        starts = np.concatenate([[0], np.cumsum(count)[:-1]])
        two = np.flatnonzero(count == 2)
        h1 = order[starts[two]]
        h2 = order[starts[two] + 1]
        consistent = he_a[h1] == he_b[h2]
        interior = two[consistent]
        h1, h2 = h1[consistent], h2[consistent]
        border_vertex = np.zeros(n, dtype=bool)
        border_vertex[edges[count == 1].ravel()] = True
        ne = len(interior)
        rows = np.concatenate([he_a[h1], he_b[h1]])
        cols = np.concatenate([np.arange(ne), np.arange(ne)])
        ve = sp.csr_matrix((np.ones(2 * ne), (rows, cols)), shape=(n, ne))
        return EdgeTopology(n, edges, face_edges, count, interior, he_f[h1], he_f[h2], he_a[h1], he_b[h1],
                            border_vertex, ve)

    return memo("edge_topology", (n, F.shape, hash(F.tobytes())), build, size=32)


def one_ring(F: np.ndarray, n_vertices: int | None = None) -> sp.csr_matrix:
    """Vertex adjacency as CSR: row i's ``indices`` are the one-ring neighbours of i (sorted)."""
    topo = edge_topology(F, n_vertices)
    e = topo.edges
    n = topo.n_vertices
    A = symmetric_adjacency(e, n)
    A.sort_indices()
    return A


def connected_components(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(n,) component label of every vertex (an isolated vertex is a component of its own)."""
    return _components(one_ring(F, n_vertices), directed=False)[1].astype(np.int64)


def edges(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(e, 2) unique undirected edges (i < j), sorted lexicographically."""
    return edge_topology(F, n_vertices).edges


def edge_faces(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(e, 2) the faces on each edge of ``edges(F)`` (lowest face index first): -1 in column 1
    on a border edge; a non-manifold edge (more than two faces) lists its first two (see
    ``non_manifold_edges``)."""
    topo = edge_topology(F, n_vertices)
    m = len(topo.face_edges)
    fe = topo.face_edges.T.reshape(-1)              # half-edge h -> edge, h = k * m + f
    f = np.tile(np.arange(m), 3)
    order = np.lexsort((f, fe))  # by edge, then by face index
    starts = np.concatenate([[0], np.cumsum(topo.edge_count)[:-1]])
    out = np.full((len(topo.edges), 2), -1, dtype=np.int64)
    out[:, 0] = f[order[starts]]
    two = topo.edge_count >= 2
    out[two, 1] = f[order[starts[two] + 1]]
    return out


def border_edges(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(e,) bool mask over ``edges(F)``: edges with exactly one face."""
    return edge_topology(F, n_vertices).edge_count == 1


def interior_edges(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(e,) bool mask over ``edges(F)``: edges with exactly two faces (orientation not checked;
    ``EdgeTopology.interior`` lists the consistently oriented ones)."""
    return edge_topology(F, n_vertices).edge_count == 2


def non_manifold_edges(F: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(e,) bool mask over ``edges(F)``: edges with more than two faces."""
    return edge_topology(F, n_vertices).edge_count > 2
