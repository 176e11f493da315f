"""DatasetContract: a dataset loads a consistent, finite, deterministic MeshCollection."""
from __future__ import annotations

import numpy as np
from fwk.testing import build


class DatasetContract:
    """Subclass with ``component`` (the dataset class) and ``params`` (a small instance)."""

    component: type = None
    params: dict = {}

    def make_cache(self, tmp_path):
        """The cache a load uses (override to share parsed raw files between tests)."""
        from fwk.cache import Cache

        return Cache(tmp_path / "cache")

    def load(self, tmp_path):
        return build(self.component, self.params).load(self.make_cache(tmp_path))

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
        assert np.asarray(col.positions).dtype == np.float64 and t.triangles.dtype == np.int64
        assert col.present.shape == (S, E) and col.present[:, 0].all()  # every subject has a neutral
        tri = t.triangles
        assert (tri[:, 0] != tri[:, 1]).all() and (tri[:, 1] != tri[:, 2]).all() and (tri[:, 0] != tri[:, 2]).all()
        for name, ix in t.regions.items():
            ix = np.asarray(ix)
            assert ix.size and ix.min() >= 0 and ix.max() < t.n_vertices, name
        assert all(0 <= int(i) < t.n_vertices for i in t.landmarks.values())

    def test_deterministic(self, tmp_path):
        a = self.load(tmp_path)
        b = self.load(tmp_path / "again")
        assert np.array_equal(np.asarray(a.positions), np.asarray(b.positions), equal_nan=True)  # a missing mesh is NaN
        assert a.subjects == b.subjects
