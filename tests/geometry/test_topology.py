import numpy as np
import pytest

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


def test_kabsch_recovers_a_known_rigid_motion_weighted_and_batched():
    from scipy.spatial.transform import Rotation

    from fwk.geometry import kabsch

    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3))
    R = Rotation.from_euler("zyx", [0.7, -1.1, 0.3]).as_matrix()
    B = A @ R.T + [1.0, -2.0, 0.5]
    R2, t2 = kabsch(A, B)
    assert np.allclose(R2, R, atol=1e-12) and np.allclose(t2, [1.0, -2.0, 0.5], atol=1e-12)
    # outliers with zero weight do not matter
    Bn = B.copy()
    Bn[:5] += 10.0
    w = np.ones(50)
    w[:5] = 0.0
    R3, t3 = kabsch(A, Bn, w)
    assert np.allclose(R3, R, atol=1e-12)
    # a mirrored target still gives a proper rotation (det +1)
    Rm, _ = kabsch(A, A * [1, 1, -1])
    assert np.linalg.det(Rm) == pytest.approx(1.0)
    Rb, tb = kabsch(np.stack([A, A]), np.stack([B, A]))
    assert np.allclose(Rb[0], R, atol=1e-12) and np.allclose(Rb[1], np.eye(3), atol=1e-12)
