"""ModelContract for reconstruction models: fit, reconstruct, save and reload, determinism.

Subclass it in a test module and set ``component`` (the model class) and ``params`` (its
constructor arguments, kept small); ``train`` overrides the test context's TrainConfig.
Models are fitted on ``tiny_fit_data()`` (synthetic heads, a few hundred vertices) with a real
run context from ``fwk.runs.make_test_context``. ``exact`` asks for bit-identical results from
a reloaded state and from a second fit with the same seed (true on CPU for every built-in);
set it to False (then ``atol`` applies) only for a model that cannot promise that.
"""
from __future__ import annotations

import io

import numpy as np


def tiny_fit_data(n_subjects=16, n_vertices=300, seed=0):
    """FitData of synthetic heads (neutral only), preprocessed, last 3 subjects as validation."""
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


def _same(a, b, exact: bool, atol: float) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and (np.array_equal(a, b) if exact else np.allclose(a, b, atol=atol))


class ModelContract:
    component: type = None
    params: dict = {}
    train: dict = {"epochs": 2, "batch_size": 8}
    exact: bool = True
    atol: float = 1e-6

    def _fit(self, tmp_path, seed=0):
        from fwk.runs import make_test_context

        data = tiny_fit_data()
        ctx = make_test_context(tmp_path, seed=seed, **self.train)
        m = self.component(**self.params)
        m.fit(data, ctx)
        return m, data

    def test_fit_reconstruct_and_reload(self, tmp_path):
        import torch

        m, data = self._fit(tmp_path)
        P = data.stack("val")
        R = m.reconstruct(P)
        assert R.shape == P.shape and np.all(np.isfinite(R))
        assert np.mean(np.abs(R - P)) < np.mean(np.abs(P)), "reconstructions unrelated to the input"
        # the run directory keeps a model as torch.save(model.state_dict())
        buf = io.BytesIO()
        torch.save(m.state_dict(), buf)
        buf.seek(0)
        m2 = self.component(**self.params)
        m2.load_state_dict(torch.load(buf, weights_only=False))
        assert _same(m2.reconstruct(P), R, self.exact, self.atol)

    def test_deterministic_for_a_seed(self, tmp_path):
        a, data = self._fit(tmp_path / "a", seed=3)
        c = type(a)
        assert isinstance(getattr(c, "name", None), str) and c.name
        assert getattr(c, "task_family", "reconstruct") == "reconstruct"
        assert (c.__doc__ or "").strip(), "the first docstring line is the `fwk list` summary"
        b, _ = self._fit(tmp_path / "b", seed=3)
        P = data.stack("val")
        assert _same(a.reconstruct(P), b.reconstruct(P), self.exact, self.atol)
        if hasattr(a, "sample"):
            S = a.sample(3, seed=1)
            assert S.shape == (3, *P.shape[1:]) and np.all(np.isfinite(S))
            assert _same(a.sample(3, seed=1), S, self.exact, self.atol)
