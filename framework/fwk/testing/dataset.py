"""DatasetContract: a dataset loads a consistent, finite, deterministic MeshCollection."""
from __future__ import annotations

import numpy as np


class DatasetContract:
    component: type = None
    params: dict = {}

    def load(self, tmp_path):
        from fwk.cache import Cache

        return self.component(**self.params).load(Cache(tmp_path / "cache"))

    def test_collection_is_consistent(self, tmp_path):
        col = self.load(tmp_path)
        t = col.template
        S, E = len(col.subjects), len(col.shape_names)
        assert col.positions.shape == (S, E, t.n_vertices, 3)
        assert col.shape_names[0] == "neutral"
        assert np.all(np.isfinite(np.asarray(col.positions)[col.present]))
        assert t.triangles.min() >= 0 and t.triangles.max() < t.n_vertices
        assert len(set(map(str, col.subjects))) == S
        assert t.poly_offsets[-1] == len(t.poly_vertices)

    def test_deterministic(self, tmp_path):
        a = self.load(tmp_path)
        b = self.load(tmp_path / "again")
        assert np.array_equal(np.asarray(a.positions), np.asarray(b.positions))
        assert a.subjects == b.subjects
