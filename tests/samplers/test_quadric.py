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
