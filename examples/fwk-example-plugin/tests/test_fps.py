"""The example sampler passes fwk's sampler contract suite (both down-samplings), picks what a
brute-force farthest-point loop picks, builds its operators and edges as naive loops do, and
serves ae (with the example's cheb conv) and a fully convolutional vcconv vae from a recipe."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from fwk.data import Template
from fwk.errors import RecipeError
from fwk.plugins import get_registry
from fwk.testing.sampler import SamplerContract, two_components
from fwk_example_plugin.fps import FarthestPointSampler, farthest_points
from recipe_runs import assert_tested, run_recipe, tiny_recipe


class TestFpsContract(SamplerContract):
    component = FarthestPointSampler


class TestFpsSelectContract(SamplerContract):
    component = FarthestPointSampler
    params = {"factors": [3, 5], "down": "select", "k": 1, "min_vertices": 2}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("sampler", "fps")
    assert e.component is FarthestPointSampler and e.plugin == "example-fps"


def brute_fps(X, m):
    """Farthest-point sampling as a plain loop: start nearest the centroid, then each time the
    point whose distance to its nearest chosen point is largest."""
    c = X.mean(0)
    chosen = [min(range(len(X)), key=lambda i: (np.linalg.norm(X[i] - c), i))]
    while len(chosen) < m:
        best, best_d = None, -1.0
        for i in range(len(X)):
            d = min(np.linalg.norm(X[i] - X[j]) for j in chosen)
            if d > best_d:
                best, best_d = i, d
        chosen.append(best)
    return chosen


def test_farthest_points_is_the_brute_force_loop():
    X = np.random.default_rng(0).normal(size=(60, 3))
    assert farthest_points(X, 15).tolist() == brute_fps(X, 15)
    assert farthest_points(X, 100).tolist() == brute_fps(X, 60)  # at most every point


def lumpy_two_components():
    """Two jittered icospheres (162 vertices each): a two-component template without the
    distance ties of a regular icosphere, whose farthest point is unique at every step."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(1)
    V = np.vstack([m.vertices, 0.4 * m.vertices + [3.0, 0.0, 0.0]])
    V = V * (1 + 0.1 * rng.random((len(V), 1)))
    return Template(V, np.vstack([m.faces, m.faces + len(m.vertices)]))


def naive_level(V, E, labels, kept, k):
    """Cells, the mean down, the inverse-distance up and the contracted edges, by loops."""
    n, nc = len(V), len(kept)
    cell = np.empty(n, dtype=np.int64)
    U = np.zeros((n, nc))
    for i in range(n):
        same = [j for j in range(nc) if labels[kept[j]] == labels[i]]
        d = {j: np.linalg.norm(V[i] - V[kept[j]]) for j in same}
        order = sorted(same, key=lambda j: (d[j], j))
        cell[i] = order[0]
        if i in kept:
            U[i, list(kept).index(i)] = 1.0
            continue
        near = order[:k]
        w = np.array([1.0 / d[j] ** 2 for j in near])
        U[i, near] = w / w.sum()
    cell[kept] = np.arange(nc)
    D = np.zeros((nc, n))
    for i in range(n):
        D[cell[i], i] = 1.0
    D /= D.sum(1, keepdims=True)
    edges = {tuple(sorted((cell[a], cell[b]))) for a, b in E if cell[a] != cell[b]}
    return cell, D, U, edges


@pytest.mark.parametrize("factors, min_vertices, k", [([4, 4], 4, 3), ([8], 30, 2)])
def test_levels_are_the_naive_loops(factors, min_vertices, k):
    t = lumpy_two_components()
    h = FarthestPointSampler(factors=factors, min_vertices=min_vertices, k=k).build(t)
    V, E, labels = t.vertices, t.edges, t.components
    for lv, (fine, coarse, D, U, f) in enumerate(zip(h.levels, h.levels[1:], h.down, h.up, factors)):
        kept = []
        for c in (0, 1):
            idx = np.flatnonzero(labels == c)
            m = max(int(np.ceil(len(idx) / f)), min(len(idx), min_vertices))
            kept += idx[brute_fps(V[idx], m)].tolist()
        kept = np.array(sorted(kept))
        assert np.array_equal(coarse.centres, kept) and coarse.n_vertices == len(kept)
        assert np.array_equal(coarse.vertices, V[kept]) and coarse.faces is None
        cell, Dn, Un, edges = naive_level(V, E, labels, kept, k)
        assert np.allclose(D.toarray(), Dn) and np.allclose(U.toarray(), Un, atol=1e-12)
        assert np.allclose(U.sum(1), 1.0) and np.allclose(D.sum(1), 1.0)  # rows sum to 1
        assert set(map(tuple, coarse.edges.tolist())) == edges
        # pool: each kept vertex's cell, itself first; unpool: the up operator's support
        for j in range(len(kept)):
            row = coarse.pool.index[j][coarse.pool.mask[j]]
            assert row[0] == kept[j] and sorted(row) == sorted(np.flatnonzero(cell == j))
        for i in range(fine.n_vertices):
            assert sorted(fine.unpool.index[i][fine.unpool.mask[i]]) == sorted(np.flatnonzero(Un[i]))
        # each component stays one connected graph, and apart from the other
        n_comp, _ = connected_components(sp.coo_matrix((np.ones(len(coarse.edges)), coarse.edges.T),
                                                       shape=(len(kept), len(kept))), directed=False)
        assert n_comp == 2
        V, E, labels = V[kept], coarse.edges, labels[kept]


def test_select_down_undoes_up():
    h = FarthestPointSampler(down="select", factors=[4, 4]).build(two_components())
    for D, U, lv in zip(h.down, h.up, h.levels[1:]):
        assert D.nnz == D.shape[0] and np.array_equal(D.indices, lv.centres)  # D[k, s_k] = 1
        assert np.allclose((D @ U).toarray(), np.eye(D.shape[0]))


def test_bad_parameters_are_recipe_errors():
    for params, words in [({"factors": [4, 1]}, "factors"), ({"factors": []}, "factors"),
                          ({"min_vertices": 0}, "min_vertices"), ({"k": 0}, "k:"), ({"down": "max"}, "down")]:
        with pytest.raises(RecipeError, match=words):
            FarthestPointSampler(**params)
    tri = Template(np.eye(3), np.array([[0, 1, 2]]))  # 3 vertices, 4 kept per component: cannot shrink
    with pytest.raises(RecipeError, match="level 1 cannot have fewer vertices"):
        FarthestPointSampler(factors=[2]).build(tri)


RECIPE = tiny_recipe("""
ae-fps: {name: ae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: fps, factors: [4, 4]}}
ae-fps-select: {name: ae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8,
                sampler: {name: fps, factors: [4, 4], down: select}}
vae-fc: {name: vae, conv: {name: vcconv}, channels: [8, 16], latent: 8, sampler: {name: fps, factors: [4, 4]},
         fully_convolutional: true}
""")


def test_fps_serves_ae_and_a_fully_convolutional_vae(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "fps.yaml", RECIPE, monkeypatch)
    assert_tested(run_dir, {"ae-fps", "ae-fps-select", "vae-fc"}, only=True)
