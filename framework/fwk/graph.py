"""Graph utilities shared by samplers and convolutions: sparse operators on (b, n, c) batches,
the symmetric adjacency of an edge list, ordered one-rings and spirals on triangle meshes.

torch is imported inside the three functions that use it: the adjacency helpers serve
``fwk.geometry``, which ``fwk --help`` loads without torch (torch costs ~1 s of import time,
measured with ``python -X importtime``)."""
from __future__ import annotations


import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path


def symmetric_adjacency(edges, n: int, weights=None) -> sp.csr_matrix:
    """(n, n) CSR adjacency of an undirected edge list (e, 2): edge k puts ``weights[k]`` (default
    1) at (i, j) and (j, i); a repeated edge sums its entries."""
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    w = np.ones(len(e)) if weights is None else np.asarray(weights)
    return sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()


def torch_sparse(M):
    """A scipy sparse matrix as a torch sparse COO tensor (float32)."""
    import torch  # deferred: see the module docstring

    M = sp.coo_matrix(M)
    idx = torch.as_tensor(np.vstack([M.row, M.col]), dtype=torch.long)
    return torch.sparse_coo_tensor(idx, torch.as_tensor(M.data, dtype=torch.float32), M.shape,
                                   check_invariants=True).coalesce()  # built once per level: checking is cheap


def sparse_apply(M, x):
    """(m, n) sparse torch matrix applied to every sample of x (b, n, c) -> (b, m, c)."""
    import torch  # deferred: see the module docstring

    b, n, c = x.shape
    # under CPU autocast (bf16) the pooling stays in the operator's precision: autocast would cast
    # the sparse operand too, and its backward then mixes dtypes
    with torch.autocast(x.device.type, enabled=False):
        y = torch.sparse.mm(M, x.to(M.dtype).transpose(0, 1).reshape(n, b * c))
    return y.reshape(M.shape[0], b, c).transpose(0, 1)


def ordered_fans(F: np.ndarray, n: int) -> tuple[list[list[int]], np.ndarray]:
    """Each vertex's one-ring in the cyclic order of its incident faces (a walk around the fan,
    counter-clockwise for consistently oriented faces) and whether the fan is closed.

    An open fan (border vertex) starts at its border neighbour, so that the walk covers it in
    one pass; a closed fan starts at its smallest neighbour index. Vertices whose fan is not a
    single disc (non-manifold) list the walk then the remaining neighbours in index order and
    count as open. Returns (rings, closed)."""
    nxt: dict[int, dict[int, int]] = {}
    for f in np.asarray(F, dtype=np.int64).reshape(-1, 3):
        a, b, c = int(f[0]), int(f[1]), int(f[2])
        nxt.setdefault(a, {})[b] = c  # around a: b -> c
        nxt.setdefault(b, {})[c] = a
        nxt.setdefault(c, {})[a] = b
    rings: list[list[int]] = []
    closed = np.zeros(n, dtype=bool)
    for v in range(n):
        m = nxt.get(v)
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
        closed[v] = not starts and not rest and m.get(cur) == start
        rings.append(ring + rest)
    return rings, closed


def ordered_one_rings(F: np.ndarray, n: int) -> list[list[int]]:
    """Each vertex's neighbours in fan order (see ``ordered_fans``)."""
    return ordered_fans(F, n)[0]


def spiral_sequences(F: np.ndarray, n: int, rings: int | None = None, max_len: int | None = None,
                     first=None, gap: int | None = None) -> list[list[int]]:
    """Full spiral of every vertex: the vertex, its one-ring in fan order, then the following
    rings, each continuing the previous one (Bouritsas et al. 2019; Gong et al. 2019).

    Ring k + 1 is built by walking ring k in order; around each of its vertices u the new
    (not yet visited) neighbours are taken in u's fan order starting just after the last visited
    one (the first visited -> new transition of the fan), so that on a regular mesh ring k + 1 is
    one continuous walk in the same rotational direction as ring k.

    rings    stop after this many rings (Neural 3DMM's "step size"); None: no limit
    max_len  stop once the spiral has at least this many entries (it is not cut here)
    first    ``first(v, ring) -> neighbour`` chooses where v's one-ring starts (default: the fan's
             own start); an open fan rotated to start elsewhere wraps across the border gap,
             where ``gap`` (if given, e.g. -1) is inserted, as Neural 3DMM does.
    """
    fans, closed = ordered_fans(F, n)
    out: list[list[int]] = []
    for v in range(n):
        r = fans[v]
        if first is not None and r:
            s = r.index(first(v, r))
            r = r[s:] + ([gap] if gap is not None and s > 0 and not closed[v] else []) + r[:s]
        seq = [v] + r
        seen = {v, *r}
        ring = [w for w in r if w != gap]
        k = 1
        while ring and (rings is None or k < rings) and (max_len is None or len(seq) < max_len):
            new = []
            for u in ring:
                fu = fans[u]
                m = len(fu)
                if m == 0:
                    continue
                vis = [w in seen for w in fu]
                s = 0
                for i in range(m):  # first visited -> new transition (cyclic for closed fans)
                    if not vis[i] and (vis[i - 1] if (i > 0 or closed[u]) else False):
                        s = i
                        break
                for w in fu[s:] + fu[:s]:
                    if w not in seen:
                        seen.add(w)
                        new.append(w)
            seq += new
            ring = new
            k += 1
        out.append(seq)
    return out


def spirals(F: np.ndarray, n: int, length: int, dilation: int = 1, first=None, pad: int | None = None) -> np.ndarray:
    """SpiralNet++ spirals (Gong et al. 2019): ``spiral_sequences`` cut to ``length * dilation``
    and taken every ``dilation``-th entry. Where rings run out (small components, borders) the
    spiral is padded with the centre vertex itself (or ``pad``): an explicit, documented choice
    instead of the reference implementation's silent k-nearest-neighbour fallback, which can
    reach into another connected component. Returns (n, length) int64."""
    need = length * dilation
    seqs = spiral_sequences(F, n, max_len=need, first=first)
    out = np.empty((n, length), dtype=np.int64)
    for v, sp_ in enumerate(seqs):
        sp_ = (sp_ + [v if pad is None else pad] * need)[:need]
        out[v] = sp_[::dilation][:length]
    return out


def bfs_distance(adj, sources) -> np.ndarray:
    """Hop distances from ``sources`` over a CSR adjacency (inf where unreachable)."""
    d = shortest_path(adj, unweighted=True, indices=np.atleast_1d(sources), directed=False)
    return d.min(axis=0) if d.ndim == 2 else d


def neighbourhoods(edges: np.ndarray, n: int, k: int, include_self: bool = True) -> np.ndarray:
    """(n, k) the vertex (optionally) then its adjacency entries in index order, padded with the
    vertex itself where there are fewer."""
    adj = symmetric_adjacency(edges, n)
    adj.sort_indices()
    out = np.empty((n, k), dtype=np.int64)
    for v in range(n):
        nb = list(adj.indices[adj.indptr[v]:adj.indptr[v + 1]])
        row = ([v] if include_self else []) + nb
        out[v] = (row + [v] * k)[:k]
    return out


def edge_index(edges: np.ndarray, n: int, self_loops: bool = True):
    """torch_geometric edge_index (2, E) with both directions (and self loops)."""
    import torch  # deferred: see the module docstring

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


def adjacency(edges, n: int) -> sp.csr_matrix:
    """(n, n) CSR 0/1 adjacency of an undirected edge list (repeated edges count once)."""
    A = symmetric_adjacency(edges, n)
    A.data[:] = 1.0
    return A


def buckets(counts, max_buckets: int = 4) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Rows of different lengths cut into at most ``max_buckets`` groups, each padded only to its
    own longest row, with the least padding (exact: dynamic programming over the distinct lengths).

    Returns (order, spans): ``order`` (n,) the rows sorted by length (stable), ``spans`` a list of
    (start, count, width): rows ``order[start:start + count]`` padded to ``width`` (at least 1)."""
    counts = np.asarray(counts, dtype=np.int64)
    order = np.argsort(counts, kind="stable")
    if len(counts) == 0:
        return order, []
    vals, freq = np.unique(counts, return_counts=True)
    ends = np.cumsum(freq)  # rows with length <= vals[v]: ends[v]
    D = len(vals)
    B = min(max_buckets, D)
    # best[k][v]: least padded size of the rows up to length vals[v] in k + 1 buckets, the last ending at v
    inf = np.iinfo(np.int64).max // 4
    best = np.full((B, D), inf, dtype=np.int64)
    back = np.zeros((B, D), dtype=np.int64)
    width = np.maximum(vals, 1)
    best[0] = ends * width
    for k in range(1, B):
        for v in range(D):
            for u in range(v):  # previous bucket ends at u
                cost = best[k - 1, u] + (ends[v] - ends[u]) * width[v]
                if cost < best[k, v]:
                    best[k, v], back[k, v] = cost, u
    k = int(np.argmin(best[:, D - 1]))
    cuts, v = [], D - 1
    while True:
        cuts.append(v)
        if k == 0:
            break
        v, k = int(back[k, v]), k - 1
    cuts = cuts[::-1]
    spans, start = [], 0
    for v in cuts:
        spans.append((start, int(ends[v]) - start, int(width[v])))
        start = int(ends[v])
    return order, spans
