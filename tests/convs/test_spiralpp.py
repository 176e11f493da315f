import numpy as np

from fwk.graph import ordered_one_rings, spirals
from fwk.plugins import get_registry
from fwk.testing.conv import ConvContract


class TestSpiralPPContract(ConvContract):
    component = get_registry().get("conv", "spiral++")
    params = {"length": 9}


def grid(n=5):
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def test_one_rings_are_cyclic_fans():
    F = grid()
    rings = ordered_one_rings(F, 25)
    centre = rings[12]
    assert sorted(centre) == [6, 7, 11, 13, 17, 18]
    # consecutive ring entries share a face with the centre (a walk around the fan)
    faces = {frozenset(map(int, f)) for f in F}
    for a, b in zip(centre, centre[1:] + centre[:1]):
        assert frozenset((12, a, b)) in faces
    corner = rings[0]  # a border vertex: an open fan starting at a border neighbour
    assert corner[0] in (1, 5) and sorted(corner) == [1, 5, 6]


def test_spirals_rings_in_order_and_padding():
    F = grid()
    S = spirals(F, 25, length=9)
    assert S[12, 0] == 12 and set(S[12, 1:7]) == {6, 7, 11, 13, 17, 18}
    assert set(S[12, 7:9]) <= set(range(25)) - {12, 6, 7, 11, 13, 17, 18}
    # a two-triangle component runs out of rings: padded with the centre, never another component
    F2 = np.vstack([F, [[25, 26, 27]]])
    S2 = spirals(F2, 28, length=9)
    assert set(S2[25]) == {25, 26, 27} and list(S2[25][3:]) == [25] * 6
    D = spirals(F, 25, length=4, dilation=2)
    full = spirals(F, 25, length=8)
    assert np.array_equal(D, full[:, ::2])


def naive_spiral(n, v, rings):
    """From the grid's geometry alone: rings by hop distance (dense BFS), each ring sorted by
    angle round v (counter-clockwise), each ring starting at the vertex that continues the
    previous ring: the first vertex strictly counter-clockwise of the previous ring's last one."""
    F = grid(n)
    N = n * n
    A = np.zeros((N, N), bool)
    for f in F:
        for a in range(3):
            A[f[a], f[(a + 1) % 3]] = A[f[(a + 1) % 3], f[a]] = True
    hop = np.full(N, -1)
    hop[v], frontier, k = 0, [v], 0
    while frontier:
        k += 1
        nxt = [u for w in frontier for u in np.flatnonzero(A[w]) if hop[u] < 0]
        for u in nxt:
            hop[u] = k
        frontier = sorted(set(nxt))
    y, x = np.divmod(np.arange(N), n)
    ang = np.arctan2(y - y[v], x - x[v])
    out, prev = [v], None
    for r in range(1, rings + 1):
        ring = sorted(np.flatnonzero(hop == r), key=lambda u: ang[u])
        if prev is None:
            s = min(np.flatnonzero(A[v]))  # the fan of a closed one-ring starts at its smallest neighbour
            start = ring.index(s)
        else:
            turn = [(ang[u] - ang[prev]) % (2 * np.pi) for u in ring]
            start = min((i for i in range(len(ring)) if turn[i] > 1e-9), key=lambda i: turn[i])
        ring = ring[start:] + ring[:start]
        out += ring
        prev = ring[-1]
    return out


def test_spirals_match_a_naive_geometric_construction_on_a_grid():
    n = 9
    F = grid(n)
    for v in (40, 30, 41, 50):  # interior vertices with three complete rings
        S = spirals(F, n * n, length=37)
        assert list(S[v]) == naive_spiral(n, v, 3), v
