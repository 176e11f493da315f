"""Neural 3DMM anchored spirals against naive constructions."""
import numpy as np
import scipy.sparse as sp

from fwk.graph import ordered_fans, spiral_sequences
from fwk.plugins import get_registry
from fwk.protocols import Level
from fwk.testing.sampler import two_components
from fwk_spiral import anchored_spirals

REG = get_registry()


def grid_level(n=6, holes=False):
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    y, x = np.divmod(np.arange(n * n), n)
    V = np.stack([x, y, -((x - 2.2) ** 2 + (y - 2.6) ** 2)], 1).astype(float)  # front-most near (2, 3)
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), 1), axis=0)
    return Level(n * n, E, F, V)


def naive_next_on_path(lv, ref):
    """Dense Floyd-Warshall over edge lengths; the neighbour of v that starts a shortest path to ref."""
    n, V = lv.n_vertices, lv.vertices
    D = np.full((n, n), np.inf)
    np.fill_diagonal(D, 0)
    for i, j in lv.edges:
        D[i, j] = D[j, i] = np.linalg.norm(V[i] - V[j])
    for k in range(n):
        D = np.minimum(D, D[:, k:k + 1] + D[k:k + 1, :])
    nxt = {}
    for v in range(n):
        if v == ref:
            continue
        nb = [j for i, j in lv.edges if i == v] + [i for i, j in lv.edges if j == v]
        nxt[v] = {u for u in nb if np.isclose(np.linalg.norm(V[u] - V[v]) + D[u, ref], D[v, ref])}
    return nxt


def test_one_ring_starts_towards_the_reference_and_runs_round_the_fan():
    lv = grid_level()
    S = anchored_spirals(lv, rings=1, dilation=1, length=12)
    ref = int(np.argmax(lv.vertices[:, 2]))
    nxt = naive_next_on_path(lv, ref)
    faces = {frozenset(map(int, f)) for f in lv.faces}
    for v in range(lv.n_vertices):
        assert S[v, 0] == v
        ring = [u for u in S[v, 1:] if u >= 0]
        if v != ref:
            assert S[v, 1] in nxt[v]
        else:
            d = np.linalg.norm(lv.vertices[ring] - lv.vertices[v], axis=1)
            assert np.isclose(d[0], d.min())
        nb = {j for i, j in lv.edges if i == v} | {i for i, j in lv.edges if j == v}
        assert set(ring) == nb
        # consecutive entries share a face with v except across one border gap (a -1)
        seq = list(S[v, 1:1 + len(ring) + (S[v, 1:] == -1).sum()])
        seq = seq[:len(ring) + seq.count(-1)]
        breaks = sum(frozenset((v, a, b)) not in faces for a, b in zip(seq, seq[1:]) if a >= 0 and b >= 0)
        assert breaks == 0


def test_border_gap_and_padding():
    lv = grid_level()
    S = anchored_spirals(lv, rings=1, dilation=1, length=12)
    fans, closed = ordered_fans(lv.faces, lv.n_vertices)
    # a border vertex whose walk starts mid-fan marks the border crossing with one -1 inside its ring
    mid = [v for v in range(lv.n_vertices) if not closed[v] and S[v, 1] != fans[v][0]]
    assert mid
    for v in mid:
        k = len(fans[v])
        assert list(S[v, 1:k + 2]).count(-1) == 1 and S[v, k + 1] != -1  # the gap lies inside the ring
        assert set(S[v, 1:k + 2]) - {-1} == set(fans[v])
    for v in range(lv.n_vertices):  # an open fan walked from its start has no gap
        if not closed[v] and S[v, 1] == fans[v][0]:
            assert -1 not in S[v, 1:len(fans[v]) + 1]
    inner = 2 * 6 + 2
    assert (S[inner, 7:] == -1).all() and (S[inner, :7] >= 0).all()


def test_default_length_is_mean_plus_two_std_and_dilation_keeps_the_centre():
    lv = grid_level(8)
    S = anchored_spirals(lv, rings=2, dilation=2)
    full = anchored_spirals(lv, rings=2, dilation=1, length=40)
    seqs = []
    for row in full:
        r = list(row)
        while r and r[-1] == -1:
            r.pop()
        seqs.append(r[:1] + r[1::2])
    lens = np.array([len(s) for s in seqs], float)
    assert S.shape[1] == int(lens.mean() + 2 * lens.std())
    for v in range(lv.n_vertices):
        s = seqs[v][:S.shape[1]]
        assert list(S[v, :len(s)]) == s and (S[v, len(s):] == -1).all()


def test_each_component_has_its_own_reference_and_no_spiral_crosses_components():
    t = two_components()
    h = REG.get("sampler", "quadric")(factors=[4]).build(t)
    for lv in h.levels:
        S = anchored_spirals(lv, rings=2, dilation=1)
        A = sp.coo_matrix((np.ones(len(lv.edges)), tuple(lv.edges.T)), shape=(lv.n_vertices,) * 2)
        from scipy.sparse.csgraph import connected_components

        _, lab = connected_components(A, directed=False)
        assert lab.max() == 1
        ok = S >= 0
        assert (lab[np.where(ok, S, 0)] == lab[:, None])[ok].all()


def test_reference_vertices_are_mapped_to_each_level():
    t = two_components()
    h = REG.get("sampler", "quadric")(factors=[4]).build(t)
    conv = REG.get("conv", "spiral")(3, 4, h, 1, rings=1, dilation=1, reference=[5])
    S = conv.index.reshape(h.levels[1].n_vertices, -1).numpy()
    V1 = h.levels[1].vertices
    ref = int(np.argmin(np.linalg.norm(V1 - t.vertices[5], axis=1)))
    d = np.linalg.norm(V1[S[ref, 1]] - V1[ref])
    nb = S[ref, 1:][S[ref, 1:] < h.levels[1].n_vertices]
    assert np.isclose(d, np.linalg.norm(V1[nb] - V1[ref], axis=1).min())


def test_spiral_sequence_rings_follow_hop_distance():
    lv = grid_level(7)
    seqs = spiral_sequences(lv.faces, lv.n_vertices, rings=3)
    from scipy.sparse.csgraph import shortest_path

    A = sp.coo_matrix((np.ones(len(lv.edges)), tuple(lv.edges.T)), shape=(lv.n_vertices,) * 2)
    D = shortest_path(A, unweighted=True, directed=False)
    for v, s in enumerate(seqs):
        d = D[v, s]
        assert np.all(np.diff(d) >= 0) and d.max() <= 3
        assert set(s) == set(np.flatnonzero(D[v] <= 3))
