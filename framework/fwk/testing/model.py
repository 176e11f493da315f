"""ModelContract for reconstruction models: fit, reconstruct, save and reload, determinism."""
from __future__ import annotations

import numpy as np


def tiny_fit_data(n_subjects=16, n_vertices=300, seed=0):
    from fwk.data.preprocess import Preprocessor
    from fwk.plugins import get_registry
    from fwk.protocols import FitData

    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=n_vertices,
                                                            shapes=["neutral"], seed=seed).load(None)
    pre = Preprocessor().fit(np.asarray(col.positions[:, 0]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    tr, va = col.select(np.arange(n_subjects - 3)), col.select(np.arange(n_subjects - 3, n_subjects))
    return FitData(col.template.with_vertices(pre.mean_neutral), tr, va, ["neutral"])


class ModelContract:
    component: type = None
    params: dict = {}
    train: dict = {"epochs": 2, "batch_size": 8}

    def _fit(self, tmp_path, seed=0):
        from fwk.runs import make_test_context

        data = tiny_fit_data()
        ctx = make_test_context(tmp_path, seed=seed, **self.train)
        m = self.component(**self.params)
        m.fit(data, ctx)
        return m, data

    def test_fit_reconstruct_and_reload(self, tmp_path):
        m, data = self._fit(tmp_path)
        P = data.stack("val")
        R = m.reconstruct(P)
        assert R.shape == P.shape and np.all(np.isfinite(R))
        m2 = self.component(**self.params)
        m2.load_state_dict(m.state_dict())
        assert np.allclose(m2.reconstruct(P), R, atol=1e-6)

    def test_deterministic_for_a_seed(self, tmp_path):
        a, data = self._fit(tmp_path / "a", seed=3)
        b, _ = self._fit(tmp_path / "b", seed=3)
        P = data.stack("val")
        assert np.allclose(a.reconstruct(P), b.reconstruct(P), atol=1e-6)
