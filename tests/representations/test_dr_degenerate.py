"""dr at near-degenerate one-rings (issue 17): a sliver (cap), a needle, a collapsed edge and a
collapsed one-ring in an otherwise well-shaped closed mesh. Features stay finite and bounded,
a tiny displacement (1e-3 of the median edge) gives tiny features, and the round trip stays
accurate away from the degenerate spot."""
import numpy as np
import pytest
import trimesh

from fwk.data import Template
from fwk.geometry.operators import cotangent_laplacian
from fwk.plugins import get_registry

DR = get_registry().get("representation", "dr")
OLD = {"regularisation": 0.0, "weight_ceiling": None}  # dr before issue 17


def base():
    m = trimesh.creation.icosphere(subdivisions=3)
    V = np.asarray(m.vertices) * [1.0, 1.2, 0.9]
    F = np.asarray(m.faces)
    L = cotangent_laplacian(V, F).tocsr()
    v = 100
    nb = L[v].indices[L[v].indices != v]
    u, w = [x for x in F[(F == v).any(1)][0] if x != v]  # triangle (v, u, w)
    el = np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1))
    return V, F, v, nb, u, w, el


def degenerate(kind):
    """The mesh with one degenerate spot at vertex v, and the 2-ring of v (where it is)."""
    V0, F, v, nb, u, w, el = base()
    V = V0.copy()
    if kind == "cap":  # v almost on the edge uw: triangle vuw is a sliver with an angle near 180 deg
        mid = (V0[u] + V0[w]) / 2
        V[v] = mid + 1e-6 * el * (V0[v] - mid) / np.linalg.norm(V0[v] - mid)
    elif kind == "needle":  # edge vu of length 1e-7 of the others: two needles
        V[v] = V0[u] + 1e-7 * (V0[v] - V0[u])
    elif kind == "collapsed-edge":  # v on u: two triangles of zero area
        V[v] = V0[u]
    elif kind == "collapsed-ring":  # every neighbour within 1e-4 of an edge of v
        V[nb] = V0[v] + 1e-4 * (V0[nb] - V0[v])
    near = np.zeros(len(V), bool)
    near[v] = near[nb] = True
    L = cotangent_laplacian(V0, F).tocsr()
    near[np.unique(L[nb].indices)] = True
    return V, F, el, near


def bend(V):
    a = 0.3 * V[:, 1]
    return np.stack([V[:, 0] * np.cos(a) - V[:, 1] * np.sin(a), V[:, 0] * np.sin(a) + V[:, 1] * np.cos(a),
                     V[:, 2] * (1 + 0.1 * V[:, 0])], 1)


KINDS = ["cap", "needle", "collapsed-edge", "collapsed-ring"]


@pytest.mark.parametrize("kind", KINDS)
def test_tiny_displacements_give_tiny_features(kind):
    V, F, el, _ = degenerate(kind)
    r = DR(scaling="none")
    r.fit(V[None], None, Template(V, F))
    assert np.abs(r.raw_features(V[None])).max() < 1e-9  # the reference encodes to zero
    rng = np.random.default_rng(0)
    P = V + rng.normal(size=(5, *V.shape)) * 1e-3 * el  # independent noise at every vertex
    f = r.raw_features(P)
    assert np.all(np.isfinite(f))
    assert np.linalg.norm(f[..., :3], axis=-1).max() < 0.05  # |log R|, rad: far below pi
    assert np.abs(f[..., 3:]).max() < 0.05  # S - I


def test_the_collapsed_ring_was_unstable_before():
    """What the regulariser fixes: without it the same 1e-3 noise rotates the collapsed one-ring
    by more than a radian."""
    V, F, el, _ = degenerate("collapsed-ring")
    r = DR(scaling="none", **OLD)
    r.fit(V[None], None, Template(V, F))
    rng = np.random.default_rng(0)
    f = r.raw_features(V + rng.normal(size=(5, *V.shape)) * 1e-3 * el)
    assert np.linalg.norm(f[..., :3], axis=-1).max() > 1.0


def test_the_needle_was_unstable_before():
    """What the weight ceiling fixes: a needle's weight (1e7) amplifies the same noise on its
    short edge into a stretch of order 0.1-1."""
    V, F, el, _ = degenerate("needle")
    rng = np.random.default_rng(0)
    P = V + rng.normal(size=(5, *V.shape)) * 1e-3 * el
    for params, big in [(OLD, True), ({"regularisation": 0.0}, False)]:
        r = DR(scaling="none", **params)
        r.fit(V[None], None, Template(V, F))
        assert (np.abs(r.raw_features(P)[..., 3:]).max() > 0.1) == big


@pytest.mark.parametrize("kind", KINDS)
def test_a_sliver_that_folds_stays_bounded(kind):
    """Move the degenerate vertex by 1e-3 of an edge, across: the sliver (or needle) flips."""
    V0, F, v, nb, u, w, el = base()
    V, _, _, _ = degenerate(kind)
    P = V.copy()
    d = np.cross(V0[w] - V0[u], V0[v] - V0[u])
    d = np.cross(d, V0[w] - V0[u])  # in the plane of vuw, across uw
    P[v] = V[v] - 1e-3 * el * d / np.linalg.norm(d)  # d points from uw towards v: this goes through uw
    r = DR(scaling="none")
    r.fit(V[None], None, Template(V, F))
    f = r.raw_features(P[None])
    assert np.all(np.isfinite(f)) and np.linalg.norm(f[..., :3], axis=-1).max() < 0.1


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_stays_accurate_elsewhere(kind):
    V0, F0 = base()[:2]
    clean = DR(scaling="none")
    clean.fit(V0[None], None, Template(V0, F0))
    Q0 = bend(V0)
    err0 = np.abs(clean.decode(clean.raw_features(Q0[None]), None, Q0[None])[0] - Q0).max()
    V, F, el, near = degenerate(kind)
    r = DR(scaling="none")
    r.fit(V[None], None, Template(V, F))
    Q = bend(V)
    X = r.decode(r.raw_features(Q[None]), None, Q[None])[0]
    assert np.all(np.isfinite(X))
    assert np.abs(X - Q)[~near].max() < 1.5 * err0  # err0: 1 % of the bend's largest displacement
    assert np.abs(X - Q)[near].max() < 3 * err0
