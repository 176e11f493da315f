import numpy as np

from fwk.geometry import connected_components, edge_topology, one_ring


def grid(n=4):
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def naive_edges(F):
    out = {}
    for fi, f in enumerate(F):
        for k in range(3):
            key = tuple(sorted((int(f[k]), int(f[(k + 1) % 3]))))
            out.setdefault(key, []).append(fi)
    return out


def test_edges_border_interior_nonmanifold_against_loops():
    F = grid(4)
    F = np.vstack([F, [[0, 1, 16]]])  # a fin on border edge (0, 1): that edge becomes non-manifold... with 2 faces
    F = np.vstack([F, [[0, 1, 17]]])  # ...and a third face makes it non-manifold
    topo = edge_topology(F, 18)
    ref = naive_edges(F)
    assert sorted(map(tuple, topo.edges.tolist())) == sorted(ref)
    counts = {tuple(e): c for e, c in zip(topo.edges.tolist(), topo.edge_count)}
    assert counts == {k: len(v) for k, v in ref.items()}
    assert {tuple(topo.edges[i]) for i in topo.non_manifold} == {(0, 1)}
    interior = {tuple(topo.edges[i]) for i in topo.interior}
    assert interior == {k for k, v in ref.items() if len(v) == 2}
    assert set(map(tuple, topo.edges[topo.border].tolist())) == {k for k, v in ref.items() if len(v) == 1}


def test_one_ring_and_components():
    F = grid(3)
    A = one_ring(F)
    ref = {i: set() for i in range(9)}
    for f in F:
        for k in range(3):
            ref[f[k]].add(int(f[(k + 1) % 3]))
            ref[f[(k + 1) % 3]].add(int(f[k]))
    for i in range(9):
        assert set(A.indices[A.indptr[i]:A.indptr[i + 1]].tolist()) == ref[i]
    two = np.vstack([F, F + 9])
    labels = connected_components(two, 19)
    assert len(set(labels[:9])) == 1 and len(set(labels[9:18])) == 1 and labels[0] != labels[9]
    assert labels[18] not in labels[:18]  # the isolated vertex
