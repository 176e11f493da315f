import numpy as np
import scipy.sparse as sp

from fwk.plugins import get_registry
from fwk.testing.sampler import SamplerContract, two_components

Quadric = get_registry().get("sampler", "quadric")


class TestQuadricContract(SamplerContract):
    component = Quadric
    params = {"factors": [4, 4, 4]}


def test_down_selects_a_subset_and_up_reproduces_linear_functions_on_coarse_surface():
    t = two_components()
    h = Quadric(factors=[4]).build(t)
    D, U = h.down[0], h.up[0]
    assert np.all(D.data == 1) and np.all(np.diff(sp.csr_matrix(D).indptr) == 1)
    kept = sp.csr_matrix(D).indices
    assert np.allclose(h.levels[1].vertices, t.vertices[kept])
    # U maps the coarse positions to points on the coarse surface close to the fine vertices
    P = U @ h.levels[1].vertices
    assert np.abs(P - t.vertices).max() < 0.1
    # a linear function of position is reproduced exactly at those surface points
    a = np.array([0.3, -1.2, 0.7])
    assert np.allclose(U @ (h.levels[1].vertices @ a), P @ a)
    # kept vertices map to themselves
    assert np.allclose((U @ D)[kept][:, kept].toarray(), np.eye(len(kept)))


def test_factor_per_component_and_cache(tmp_path):
    from fwk.cache import Cache

    t = two_components()
    h = Quadric(factors=[4, 4]).build(t, Cache(tmp_path))
    n = [l.n_vertices for l in h.levels]
    assert abs(n[1] - t.n_vertices / 4) <= 2 and abs(n[2] - n[1] / 4) <= 2
    h2 = Quadric(factors=[4, 4]).build(t, Cache(tmp_path))
    assert [l.n_vertices for l in h2.levels] == n


def test_up_weights_are_the_closest_point_on_the_coarse_surface_of_the_own_component():
    import igl

    t = two_components()
    h = Quadric(factors=[4]).build(t)
    U = sp.csr_matrix(h.up[0])
    Vc, Fc = h.levels[1].vertices, h.levels[1].faces
    assert U.data.min() >= -1e-12 and np.diff(U.indptr).max() <= 3
    P = U @ Vc
    n0 = t.n_vertices // 2
    for sl, lab in ((slice(0, n0), 0), (slice(n0, None), 1)):
        # naive: libigl's exact closest point over all of that component's coarse triangles
        keep = (Vc[Fc[:, 0], 0] > 1.5) == bool(lab)
        d2, _, _ = igl.point_mesh_squared_distance(t.vertices[sl], Vc, Fc[keep])
        assert np.allclose(((P[sl] - t.vertices[sl]) ** 2).sum(1), d2, atol=1e-12)


def test_borders_and_a_tiny_component():
    """An open grid (closest points on border edges) next to a single triangle."""
    from fwk.data import Template

    n = 12
    y, x = np.divmod(np.arange(n * n), n)
    V = np.stack([x, y, 0.05 * np.sin(x + y)], 1).astype(float)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    V = np.vstack([V, [[20, 0, 0], [21, 0, 0], [20, 1, 0]]])
    F = np.vstack([F, [[n * n, n * n + 1, n * n + 2]]])
    t = Template(V, F)
    h = Quadric(factors=[4, 4]).build(t)
    for D, U, lv in zip(h.down, h.up, h.levels[1:]):
        assert np.allclose(np.asarray(U.sum(1)).ravel(), 1)
        assert (lv.vertices[:, 0] >= 20).sum() == 3  # the triangle keeps all its vertices
    # a linear function is reproduced at the up-sampled points, on the border too
    U = h.up[0]
    P = U @ h.levels[1].vertices
    a = np.array([0.5, -0.25, 2.0])
    assert np.allclose(U @ (h.levels[1].vertices @ a), P @ a)
    assert np.abs(P[:, :2] - V[:, :2]).max() < 1.0
