import numpy as np
import scipy.sparse as sp

from fwk.plugins import get_registry
from fwk.testing.sampler import SamplerContract, two_components

Simple = get_registry().get("sampler", "simple")


class TestSimpleContract(SamplerContract):
    component = Simple
    params = {"levels": 3}


def test_centres_spacing_and_coverage():
    from fwk_simple import _adj, _within, centres_bfs

    t = two_components()
    A = _adj(t.edges, t.n_vertices)
    C = centres_bfs(A, 2)
    W1 = _within(A, 1)
    # no two centres adjacent (stride 2), every vertex within one hop of a centre
    assert W1[C][:, C].nnz == len(C)
    assert (np.asarray(W1[C].sum(0)).ravel() > 0).all()


def test_neighbourhoods_match_operators():
    t = two_components()
    h = Simple(levels=2).build(t)
    for i in range(2):
        nxt, lv = h.levels[i + 1], h.levels[i]
        idx, mask = nxt.pool.index, nxt.pool.mask
        D = sp.csr_matrix(h.down[i])
        for c in range(0, nxt.n_vertices, 7):
            assert set(idx[c][mask[c]]) == set(D.indices[D.indptr[c]:D.indptr[c + 1]])
        assert (idx[:, 0] == nxt.centres).all()
        assert lv.conv.index.shape[0] == lv.n_vertices and (lv.conv.index[:, 0] == np.arange(lv.n_vertices)).all()
        assert lv.unpool.mask.any(1).all()


def test_per_level_strides_and_radii():
    import pytest

    from fwk.errors import RecipeError

    t = two_components()
    h = Simple(levels=2, stride=[3, 2], radius=[2, 1]).build(t)
    from fwk_simple import _adj, _within

    A0 = _adj(t.edges, t.n_vertices)
    C = h.levels[1].centres
    assert _within(A0, 2)[C][:, C].nnz == len(C)  # stride 3: centres at least 3 hops apart
    assert h.levels[0].conv.mask.sum(1).max() == _within(A0, 2).getnnz(1).max()
    A1 = _adj(h.levels[1].edges, h.levels[1].n_vertices)
    assert h.levels[1].conv.mask.sum(1).max() == _within(A1, 1).getnnz(1).max()
    with pytest.raises(RecipeError):
        Simple(levels=2, stride=[3], radius=1)
