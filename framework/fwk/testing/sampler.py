"""SamplerContract: a hierarchy of sparse down/up operators that preserves components."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from fwk.testing import build


def two_components():
    """Two icospheres of different size: a template with two connected components."""
    import trimesh

    from fwk.data import Template

    m = trimesh.creation.icosphere(subdivisions=3)
    V = np.vstack([m.vertices, 0.4 * m.vertices + [3.0, 0.0, 0.0]])
    F = np.vstack([m.faces, m.faces + len(m.vertices)])
    return Template(V, F)


class SamplerContract:
    component: type = None
    params: dict = {}

    def build(self):
        t = two_components()
        return t, build(self.component, self.params).build(t)

    def test_levels_and_sparse_operators(self):
        t, h = self.build()
        assert h.levels[0].n_vertices == t.n_vertices
        assert len(h.down) == len(h.up) == len(h.levels) - 1
        for i, (D, U) in enumerate(zip(h.down, h.up)):
            a, b = h.levels[i].n_vertices, h.levels[i + 1].n_vertices
            assert sp.issparse(D) and sp.issparse(U)
            assert D.shape == (b, a) and U.shape == (a, b) and b < a
            assert D.nnz < 0.5 * a * b + 1 and U.nnz < 0.5 * a * b + 1  # never dense
            assert np.all(np.isfinite(D.data)) and np.all(np.isfinite(U.data))

    def test_up_rows_are_partitions_of_unity(self):
        _, h = self.build()
        for U in h.up:
            assert np.allclose(np.asarray(U.sum(axis=1)).ravel(), 1.0)

    def test_components_are_kept_apart(self):
        t, h = self.build()
        n0 = t.n_vertices // 2
        labels = (np.arange(t.n_vertices) >= n0).astype(int)
        for D, U in zip(h.down, h.up):
            # every coarse vertex draws from one component, every fine vertex from one too
            Dc = sp.coo_matrix(D)
            coarse_label = np.full(D.shape[0], -1)
            coarse_label[Dc.row] = labels[Dc.col]
            assert (coarse_label >= 0).all()
            Uc = sp.coo_matrix(U)
            assert np.all(labels[Uc.row] == coarse_label[Uc.col])
            labels = coarse_label
        assert set(labels) == {0, 1}  # both components survive to the coarsest level

    def test_levels_are_well_formed(self):
        _, h = self.build()
        for lv in h.levels:
            e = np.asarray(lv.edges)
            assert e.ndim == 2 and e.shape[1] == 2 and (e[:, 0] < e[:, 1]).all() and e.max() < lv.n_vertices
            assert len(np.unique(e, axis=0)) == len(e)
            if lv.faces is not None:
                assert np.asarray(lv.faces).max() < lv.n_vertices
            if lv.vertices is not None:
                assert np.asarray(lv.vertices).shape == (lv.n_vertices, 3)
        for D in h.down:  # every coarse vertex draws on the fine level with non-negative weights
            assert D.data.min() >= 0 and (np.diff(sp.csr_matrix(D).indptr) > 0).all()

    def test_cached_build_equals_a_fresh_one(self, tmp_path):
        from fwk.cache import Cache

        t = two_components()
        a = build(self.component, self.params).build(t, Cache(tmp_path))
        b = build(self.component, self.params).build(t, Cache(tmp_path))
        c = build(self.component, self.params).build(t)
        for x in (b, c):
            assert [lv.n_vertices for lv in x.levels] == [lv.n_vertices for lv in a.levels]
            for D1, D2 in zip(a.down + a.up, x.down + x.up):
                assert (abs(D1 - D2) > 1e-12).nnz == 0
