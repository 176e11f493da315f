"""BlendshapeModelContract: the suite every model playing ``fwk.protocols.BlendshapeModel`` passes.

Subclass it in a test module and set ``component`` (the model class) and ``params`` (its
constructor arguments, kept small); ``train`` overrides the test context's TrainConfig::

    from fwk.testing.blendshapes import BlendshapeModelContract

    class TestMyModel(BlendshapeModelContract):
        component = MyModel
        params = {"network": {"name": "vae", "channels": [8], "latent": 4}}

Models are fitted on ``tiny_blendshape_data()`` (synthetic heads with a neutral and two
expressions, a few hundred vertices, preprocessed as the blendshapes task does) with a real run
context from ``fwk.runs.make_test_context``. The suite checks:

* the roles: an instance plays ``Model`` and ``BlendshapeModel``; the class declares every
  member of the role (``fwk.protocols.plays``: ``fwk apply`` chooses a model from its class);
  ``expressions`` is None until set or fitted, then lists what the model was trained for;
* ``predict`` and ``predict_all`` (with and without ``target``) agree, (b, n, 3) and finite (to
  ``atol`` where the class sets ``batches_expressions``: its ``predict_all`` runs the expressions
  through one network pass, whose matrix products round differently from one expression's);
* the state round trip: ``model.state_dict()`` written and read back in the run directory's safe
  format (``fwk.safeio``: tensors, arrays and plain data only) into a new instance through
  ``load_state_dict(d, ctx=None)`` gives the same predictions;
* determinism: a second fit with the same seed gives the same predictions (both fits with one
  thread count, ``fwk.testing.fixed_threads``: counts change the order of floating-point sums);
* where played, ``CompositeModel.parts`` (labelled (b, n, 3) predictions, the labels of
  ``part_models``) and
  ``CutSelectingModel`` (a chosen ``k`` per expression, the sweep that chose it).

``exact`` asks for bit-identical results (true on CPU for every built-in); set it to False
(then ``atol`` applies) only for a model that cannot promise that.
"""
from __future__ import annotations


import numpy as np
import pytest
from fwk.testing import build, fixed_threads

from ..data.preprocess import Preprocessor
from ..plugins import get_registry
from ..protocols import (BLENDSHAPES, BlendshapeModel, CompositeModel, CutSelectingModel, FitData, Model, Packable,
                         plays)
from ..runs import make_test_context
from .model import safe_round_trip, same

#: the two expressions of the tiny data
EXPRESSIONS = ["mouth-wide", "face-compression"]


def tiny_blendshape_data(n_subjects: int = 10, n_vertices: int = 250, expressions=tuple(EXPRESSIONS),
                         n_val: int = 3, seed: int = 0, dataset: str = "synthetic-heads") -> FitData:
    """FitData of a generated dataset (synthetic heads) with a neutral and ``expressions``,
    preprocessed on the training subjects as the blendshapes task does (centred, registered,
    scaled); the last ``n_val`` subjects are the validation split."""
    col = get_registry().get("dataset", dataset)(n_subjects=n_subjects, n_vertices=n_vertices,
                                                 shapes=["neutral", *expressions], seed=seed).load(None)
    tr = n_subjects - n_val
    pre = Preprocessor().fit(np.asarray(col.positions[:tr, 0]), np.asarray(col.positions[:tr]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    return FitData(col.template.with_vertices(pre.mean_neutral), col.select(np.arange(tr)),
                   col.select(np.arange(tr, n_subjects)), ["neutral", *expressions])


class BlendshapeModelContract:
    component: type = None
    params: dict = {}
    train: dict = {"epochs": 1, "batch_size": 4}
    exact: bool = True
    atol: float = 1e-6
    batches_expressions: bool = False  # predict_all in one network pass: agrees with predict to atol

    # ------------------------------------------------------------------ helpers
    def _fit(self, tmp_path, seed: int = 0):
        data = tiny_blendshape_data()
        m = build(self.component, self.params)
        with fixed_threads():  # the determinism test compares two fits bit for bit
            m.fit(data, make_test_context(tmp_path, seed=seed, **self.train))
        return m, data

    @staticmethod
    def _val(data, e):
        """(neutrals, ground truth) of the validation subjects that have expression ``e``."""
        col = data.val
        j0, je = col.shape_index("neutral"), col.shape_index(e)
        ok = col.present[:, j0] & col.present[:, je]
        return np.asarray(col.positions[ok, j0]), np.asarray(col.positions[ok, je])

    def _predictions(self, m, data) -> dict:
        return {e: m.predict(self._val(data, e)[0], e) for e in EXPRESSIONS}

    @pytest.fixture(scope="class")
    @classmethod
    def fitted(cls, tmp_path_factory):
        """One fit (seed 0) shared by the tests of a class (a classmethod: see GenerativeModelContract)."""
        return cls()._fit(tmp_path_factory.mktemp(f"{cls.component.name}-fit"))

    # ------------------------------------------------------------------ roles
    def test_declares_the_blendshape_role(self):
        c = self.component
        assert isinstance(getattr(c, "name", None), str) and c.name
        assert c.task_family == BLENDSHAPES
        assert (c.__doc__ or "").strip(), "the first docstring line is the `fwk list` summary"
        assert plays(c, BlendshapeModel), "declare every member of the role on the class (fwk apply checks classes)"
        m = c(**self.params)
        assert isinstance(m, Model) and isinstance(m, BlendshapeModel)
        if "expressions" not in self.params:
            assert m.expressions is None, "expressions: None until set or fitted"
        for role in (CompositeModel, CutSelectingModel):
            assert plays(c, role) == isinstance(m, role), f"{role.__name__}: declared on the class and the instance alike"

    # ------------------------------------------------------------------ predictions
    def test_fit_predict_and_predict_all_agree(self, fitted):
        m, data = fitted
        assert sorted(m.expressions) == sorted(EXPRESSIONS)
        e0 = EXPRESSIONS[0]
        N, G = self._val(data, e0)
        P = m.predict(N, e0)
        assert P.shape == N.shape and np.all(np.isfinite(P))
        assert np.abs(P - G).mean() < np.abs(G).mean(), "predictions unrelated to the expression"
        both = m.predict_all(N, EXPRESSIONS)
        assert list(both) == EXPRESSIONS
        for e in EXPRESSIONS:
            assert same(both[e], m.predict(N, e), self.exact and not self.batches_expressions, self.atol), e
        # with the ground truth as target (how the blendshapes task scores)
        targets = {e: self._val(data, e)[1] for e in EXPRESSIONS}
        with_t = m.predict_all(N, EXPRESSIONS, target=targets)
        for e in EXPRESSIONS:
            assert with_t[e].shape == N.shape and np.all(np.isfinite(with_t[e]))
            assert same(with_t[e], m.predict(N, e, target=targets[e]), self.exact and not self.batches_expressions,
                        self.atol), e
        # one neutral at a time gives the same as the batch
        assert same(m.predict(N[:1], e0), P[:1], False, max(self.atol, 1e-5))

    def test_state_round_trip(self, fitted):
        m, data = fitted
        # the run directory keeps models/<label>.safetensors like this (fwk.safeio; never a pickle)
        m2 = build(self.component, self.params)
        m2.load_state_dict(safe_round_trip(m.state_dict()), ctx=None)
        assert list(m2.expressions) == list(m.expressions)
        a, b = self._predictions(m, data), self._predictions(m2, data)
        for e in EXPRESSIONS:
            assert same(b[e], a[e], self.exact, self.atol), e
        if isinstance(m, CutSelectingModel):
            assert m2.k == m.k and m2.sweep == m.sweep

    def test_packed_state(self, fitted):
        """Optional role ``Packable``: the packed state, through the safe format and narrowed and
        widened as ``fwk pack`` stores it and fwk loads it (``--precision mixed``), loads into a
        model predicting as this one does (to 1e-4 of the largest predicted displacement)."""
        m, data = fitted
        if not isinstance(m, Packable):
            pytest.skip(f"{self.component.name} does not play Packable")
        from ..safeio import narrow, widen

        m2 = build(self.component, self.params)
        m2.load_state_dict(widen(safe_round_trip(narrow(m.packed_state(), "mixed"))), ctx=None)
        assert list(m2.expressions) == list(m.expressions)
        a, b = self._predictions(m, data), self._predictions(m2, data)
        for e in EXPRESSIONS:
            N = self._val(data, e)[0]
            scale = max(float(np.abs(a[e] - N).max()), 1e-12)
            assert float(np.abs(b[e] - a[e]).max()) <= 1e-4 * scale, e
        if isinstance(m, CutSelectingModel):
            assert m2.k == m.k

    def test_deterministic_for_a_seed(self, fitted, tmp_path):
        m, data = fitted
        again, _ = self._fit(tmp_path, seed=0)
        a, b = self._predictions(m, data), self._predictions(again, data)
        for e in EXPRESSIONS:
            assert same(b[e], a[e], self.exact, self.atol), e

    # ------------------------------------------------------------------ optional roles
    def test_composite_parts(self, fitted):
        m, data = fitted
        if not isinstance(m, CompositeModel):
            pytest.skip(f"{self.component.name} is not a CompositeModel")
        for e in EXPRESSIONS:
            N, G = self._val(data, e)
            parts = m.parts(N, e, target=G)
            assert parts and all(isinstance(k, str) and k for k in parts)
            for k, P in parts.items():
                assert P.shape == N.shape and np.all(np.isfinite(P)), k
            assert list(m.part_models()) == list(parts), "part_models and parts carry the same labels"

    def test_cut_selection(self, fitted):
        m, data = fitted
        if not isinstance(m, CutSelectingModel):
            pytest.skip(f"{self.component.name} is not a CutSelectingModel")
        n = data.template.n_vertices
        assert sorted(m.k) == sorted(EXPRESSIONS)
        for e in EXPRESSIONS:
            assert isinstance(m.k[e], int) and 0 <= m.k[e] <= n
        for e, s in m.sweep.items():  # empty when the recipe fixes k
            assert e in EXPRESSIONS and isinstance(s, dict)
            assert s["chosen"] == m.k[e] and s["chosen"] in s["ks"]
