"""Graph utilities shared by samplers and convolutions: sparse operators on (b, n, c) batches,
ordered one-rings and spirals on triangle meshes."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def torch_sparse(M):
    """A scipy sparse matrix as a torch sparse COO tensor (float32)."""
    import torch

    M = sp.coo_matrix(M)
    idx = torch.as_tensor(np.vstack([M.row, M.col]), dtype=torch.long)
    return torch.sparse_coo_tensor(idx, torch.as_tensor(M.data, dtype=torch.float32), M.shape,
                                   check_invariants=True).coalesce()  # built once per level: checking is cheap


def sparse_apply(M, x):
    """(m, n) sparse torch matrix applied to every sample of x (b, n, c) -> (b, m, c)."""
    import torch

    b, n, c = x.shape
    y = torch.sparse.mm(M, x.transpose(0, 1).reshape(n, b * c))
    return y.reshape(M.shape[0], b, c).transpose(0, 1)


def ordered_one_rings(F: np.ndarray, n: int) -> list[list[int]]:
    """Each vertex's neighbours in the cyclic order of its incident faces (a fan walk), for
    border vertices starting at a border neighbour; vertices of non-manifold fans fall back to
    sorted order after the walk."""
    nxt = {}
    for f in np.asarray(F):
        for k in range(3):
            a, b, c = int(f[k]), int(f[(k + 1) % 3]), int(f[(k + 2) % 3])
            nxt.setdefault(a, {})[b] = c  # around a: b -> c
    rings = []
    for v in range(n):
        m = nxt.get(v, {})
        if not m:
            rings.append([])
            continue
        targets = set(m.values())
        starts = [b for b in m if b not in targets]  # a border neighbour starts an open fan
        start = min(starts) if starts else min(m)
        ring, cur, seen = [start], start, {start}
        while cur in m and m[cur] not in seen:
            cur = m[cur]
            ring.append(cur)
            seen.add(cur)
        rest = sorted((set(m) | targets) - seen)
        rings.append(ring + rest)
    return rings


def spirals(F: np.ndarray, n: int, length: int, dilation: int = 1, first=None, pad: int | None = None) -> np.ndarray:
    """SpiralNet++ spirals (Gong et al. 2019): the vertex, its one-ring in mesh order, then the
    following rings (each ordered by walking the previous ring), cut to ``length * dilation``
    and taken every ``dilation``. Where rings run out (small components, borders) the spiral is
    padded with the centre vertex itself: an explicit, documented choice instead of the
    reference implementation's silent k-nearest-neighbour fallback. Returns (n, length)."""
    rings = ordered_one_rings(F, n)
    if first is not None:  # rotate each cyclic ring to start at the neighbour chosen by first(v, ring)
        rings = [r[r.index(first(v, r)):] + r[:r.index(first(v, r))] if r else r for v, r in enumerate(rings)]
    need = length * dilation
    out = np.empty((n, length), dtype=np.int64)
    for v in range(n):
        sp_, seen = [v], {v}
        frontier = [v]
        while len(sp_) < need and frontier:
            nf = []
            for u in frontier:
                for w in rings[u]:
                    if w not in seen:
                        seen.add(w)
                        sp_.append(w)
                        nf.append(w)
            frontier = nf
        sp_ = (sp_ + [v if pad is None else pad] * need)[:need]
        out[v] = sp_[::dilation][:length]
    return out


def bfs_distance(adj, sources) -> np.ndarray:
    """Hop distances from ``sources`` over a CSR adjacency (inf where unreachable)."""
    from scipy.sparse.csgraph import shortest_path

    d = shortest_path(adj, unweighted=True, indices=np.atleast_1d(sources), directed=False)
    return d.min(axis=0) if d.ndim == 2 else d


def neighbourhoods(edges: np.ndarray, n: int, k: int, include_self: bool = True) -> np.ndarray:
    """(n, k) the vertex (optionally) then its adjacency entries in index order, padded with the
    vertex itself where there are fewer."""
    adj = sp.coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                        shape=(n, n)).tocsr()
    adj.sort_indices()
    out = np.empty((n, k), dtype=np.int64)
    for v in range(n):
        nb = list(adj.indices[adj.indptr[v]:adj.indptr[v + 1]])
        row = ([v] if include_self else []) + nb
        out[v] = (row + [v] * k)[:k]
    return out


def edge_index(edges: np.ndarray, n: int, self_loops: bool = True):
    """torch_geometric edge_index (2, E) with both directions (and self loops)."""
    import torch

    e = np.r_[edges, edges[:, ::-1]]
    if self_loops:
        e = np.r_[e, np.stack([np.arange(n), np.arange(n)], 1)]
    return torch.as_tensor(e.T.copy(), dtype=torch.long)


def reach(A, hops: int):
    """Boolean-pattern CSR of the vertices within ``hops`` of each vertex (itself included)."""
    n = A.shape[0]
    R = sp.identity(n, format="csr", dtype=np.float64)
    step = (sp.csr_matrix(A) + sp.identity(n, format="csr")).tocsr()
    for _ in range(hops):
        R = (R @ step).tocsr()
        R.data[:] = 1.0
    return R


def padded_rows(R, first=None):
    """Rows of a CSR pattern as (n, K) padded indices and a boolean mask; ``first[i]`` leads row i."""
    R = sp.csr_matrix(R)
    R.sort_indices()
    counts = np.diff(R.indptr)
    K = int(counts.max()) if len(counts) else 1
    idx = np.zeros((R.shape[0], K), dtype=np.int64)
    mask = np.zeros((R.shape[0], K), dtype=bool)
    for i in range(R.shape[0]):
        row = list(R.indices[R.indptr[i]:R.indptr[i + 1]])
        if first is not None and first[i] in row:
            row.remove(first[i])
            row.insert(0, first[i])
        idx[i, :len(row)] = row
        mask[i, :len(row)] = True
        idx[i, len(row):] = row[0] if row else 0
    return idx, mask


def adjacency(edges, n: int):
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    A.data[:] = 1.0
    return A
