"""ModelContract for reconstruction models (``fwk.protocols.ReconstructionModel``): the role, fit,
reconstruct, save and reload (through the run directory's safe format, ``fwk.safeio``: a state
holds tensors, NumPy arrays and plain data only), determinism.

Subclass it in a test module and set ``component`` (the model class) and ``params`` (its recipe
parameters, kept small; nested components as in a recipe: ``{"network": {"name": "vae", ...}}``);
``train`` overrides the test context's TrainConfig. The model is built as a recipe builds it
(``fwk.recipes.validate_params``: nested specs resolved, defaults given by name become specs) and
fitted on ``tiny_fit_data()`` (synthetic heads, a few hundred vertices) with a real run context
from ``fwk.runs.make_test_context``. ``exact`` asks for bit-identical results from a reloaded state
and from a second fit with the same seed (true on CPU for every built-in); set it to False (then
``atol`` applies) only for a model that cannot promise that.

``FittedModel`` (building and fitting) is shared with the generative and band-model suites of
``fwk.testing.generative``.
"""
from __future__ import annotations

import numpy as np
import torch

from fwk.data.preprocess import Preprocessor
from fwk.plugins import get_registry
from fwk.protocols import RECONSTRUCT, FitData, GenerativeModel, ReconstructionModel, plays
from fwk.testing import build, fixed_threads
from fwk.runs import make_test_context
from fwk.safeio import dumps_state, loads_state


def tiny_fit_data(n_subjects=16, n_vertices=300, seed=0, dataset: str = "synthetic-heads"):
    """FitData of synthetic heads (neutral only), preprocessed, last 3 subjects as validation."""
    col = get_registry().get("dataset", dataset)(n_subjects=n_subjects, n_vertices=n_vertices,
                                                 shapes=["neutral"], seed=seed).load(None)
    pre = Preprocessor().fit(np.asarray(col.positions[:, 0]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    tr, va = col.select(np.arange(n_subjects - 3)), col.select(np.arange(n_subjects - 3, n_subjects))
    return FitData(col.template.with_vertices(pre.mean_neutral), tr, va, ["neutral"])


def assert_same_state(a, b, where: str = "state") -> None:
    """``b`` (a state read back) equals ``a`` (the state saved): the same nesting, NumPy arrays as
    NumPy arrays and tensors as tensors of the same dtype, shape and bits, the same plain values."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(b) == list(a), f"{where}: keys {list(a)} != {list(b)}"
        for k in a:
            assert_same_state(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert type(b) is type(a) and len(b) == len(a), f"{where}: {type(a).__name__} of {len(a)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_state(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor) and a.layout == torch.sparse_coo:
        assert isinstance(b, torch.Tensor) and b.layout == a.layout and b.dtype == a.dtype and b.shape == a.shape, where
        assert torch.equal(a.detach().cpu().coalesce().indices(), b.indices()), where
        assert torch.equal(a.detach().cpu().coalesce().values(), b.values()), where
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and b.layout == a.layout and b.dtype == a.dtype and b.shape == a.shape, where
        assert torch.equal(a.detach().cpu(), b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                                    and torch.equal(a[~a.isnan()], b[~b.isnan()])), where
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and b.dtype == a.dtype and b.shape == a.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    else:
        assert type(b) is type(a) and (b == a or (a != a and b != b)), f"{where}: {a!r} != {b!r}"


def safe_round_trip(state):
    """``state`` written in the run directory's safe format (``fwk.safeio``: tensors, arrays and
    plain data, never a pickle) and read back, checked equal to the original; a state holding
    anything else fails here (``TypeError`` naming where it sits)."""
    back, _ = loads_state(dumps_state(state))
    assert_same_state(state, back)
    return back


def same(a, b, exact: bool, atol: float) -> bool:
    """Equal shapes and values: bit-identical when ``exact``, else to ``atol``."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and (np.array_equal(a, b) if exact else np.allclose(a, b, atol=atol))


class FittedModel:
    """Builds ``component`` from ``params`` as a recipe would and fits it on ``tiny_fit_data()``."""

    component: type = None
    params: dict = {}
    train: dict = {"epochs": 2, "batch_size": 8}
    exact: bool = True
    atol: float = 1e-6

    def make(self):
        """A fresh, unfitted instance (nested components resolved against the plugin registry)."""
        return build(self.component, self.params)

    def _fit(self, tmp_path, seed=0):
        data = tiny_fit_data()
        ctx = make_test_context(tmp_path, seed=seed, **self.train)
        m = self.make()
        with fixed_threads():  # the determinism test compares two fits bit for bit
            m.fit(data, ctx)
        return m, data


class ModelContract(FittedModel):
    """Reconstruction models: role, reconstruction, state round trip, determinism for a seed."""

    def test_fit_reconstruct_and_reload(self, tmp_path):
        m, data = self._fit(tmp_path)
        assert isinstance(m, ReconstructionModel)
        P = data.stack("val")
        R = m.reconstruct(P)
        assert R.shape == P.shape and np.all(np.isfinite(R))
        assert np.mean(np.abs(R - P)) < np.mean(np.abs(P)), "reconstructions unrelated to the input"
        # the run directory keeps a model's state_dict in fwk.safeio's format (never a pickle); a
        # reopened run loads it with its context, `fwk.lifecycle` without one where there is none
        state = m.state_dict()
        for ctx in (None, make_test_context(tmp_path / "reload")):
            m2 = self.make()
            m2.load_state_dict(safe_round_trip(state), ctx=ctx)
            assert same(m2.reconstruct(P), R, self.exact, self.atol)

    def test_deterministic_for_a_seed(self, tmp_path):
        a, data = self._fit(tmp_path / "a", seed=3)
        c = type(a)
        assert isinstance(c.name, str) and c.name
        assert c.task_family == RECONSTRUCT
        assert plays(c, ReconstructionModel), "the class must define every member of ReconstructionModel"
        assert isinstance(a, ReconstructionModel)
        assert (c.__doc__ or "").strip(), "the first docstring line is the `fwk list` summary"
        b, _ = self._fit(tmp_path / "b", seed=3)
        P = data.stack("val")
        assert same(a.reconstruct(P), b.reconstruct(P), self.exact, self.atol)
        if isinstance(a, GenerativeModel):
            S = a.sample(3, seed=1)
            assert S.shape == (3, *P.shape[1:]) and np.all(np.isfinite(S))
            assert same(a.sample(3, seed=1), S, self.exact, self.atol)
            assert same(b.sample(3, seed=1), S, self.exact, self.atol)
