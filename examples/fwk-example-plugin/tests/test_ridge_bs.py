"""The example model ridge-bs passes fwk's blendshape-model contract suite, its predictions equal
the dense normal-equation solution of the ridge problem, and it runs in a blendshapes recipe
beside Deformation Transfer."""
import json

import numpy as np
import pytest

from fwk.errors import DataError, RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import BlendshapeModel
from fwk.testing.blendshapes import EXPRESSIONS, BlendshapeModelContract, tiny_blendshape_data
from fwk_example_plugin.ridge_bs import RidgeBlendshapes
from recipe_runs import run_recipe


class TestRidgeBlendshapesContract(BlendshapeModelContract):
    component = RidgeBlendshapes
    params = {"n_components": 4, "ridge_weight": 0.5}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("model", "ridge-bs")
    assert e.component is RidgeBlendshapes and e.plugin == "example-ridge-bs"


@pytest.fixture(scope="module")
def data():
    return tiny_blendshape_data()


def _columns(col, e):
    j0, je = col.shape_index("neutral"), col.shape_index(e)
    ok = col.present[:, j0] & col.present[:, je]
    return np.asarray(col.positions[ok, j0]), np.asarray(col.positions[ok, je])


def _dense_reference(data, e, k, lam, neutrals):
    """The ridge problem written out: design matrix [1, c(x)] of whitened neutral PCA codes, the
    intercept unpenalised, solved from its normal equations (X^T X + diag(0, lam, ..)) theta = X^T D."""
    col = data.train
    Nall = np.asarray(col.positions[:, col.shape_index("neutral")]).reshape(len(col.subjects), -1)
    mu = Nall.mean(0)
    _, s, Vt = np.linalg.svd(Nall - mu, full_matrices=False)
    sd = s[:k] / np.sqrt(len(Nall) - 1)

    def code(N):
        return (N.reshape(len(N), -1) - mu) @ Vt[:k].T / sd

    N, E = _columns(col, e)
    X = np.hstack([np.ones((len(N), 1)), code(N)])
    D = (E - N).reshape(len(N), -1)
    theta = np.linalg.solve(X.T @ X + np.diag([0.0] + [lam] * k), X.T @ D)
    Xq = np.hstack([np.ones((len(neutrals), 1)), code(neutrals)])
    return neutrals + (Xq @ theta).reshape(neutrals.shape)


@pytest.mark.parametrize("k,lam", [(3, 0.1), (6, 2.0), (6, 1e3)])
def test_predictions_equal_the_normal_equations(data, k, lam):
    m = RidgeBlendshapes(n_components=k, ridge_weight=lam)
    m.fit(data)
    assert m.expressions == EXPRESSIONS
    N = np.concatenate([_columns(data.val, EXPRESSIONS[0])[0], _columns(data.train, EXPRESSIONS[0])[0][:2]])
    out = m.predict_all(N, EXPRESSIONS)
    for e in EXPRESSIONS:
        assert out[e].dtype == np.float64 and out[e].shape == N.shape
        assert np.allclose(out[e], _dense_reference(data, e, k, lam, N), atol=1e-10), e


def test_limits_of_the_ridge_weight(data):
    N, E = _columns(data.train, EXPRESSIONS[0])
    # lambda = 0 with every component (m - 1 codes and an intercept for m subjects): least squares interpolates
    exact = RidgeBlendshapes(ridge_weight=0.0)
    exact.fit(data)
    assert np.allclose(exact.predict(N, EXPRESSIONS[0]), E, atol=1e-8)
    # lambda -> infinity: every neutral gets the mean displacement
    flat = RidgeBlendshapes(ridge_weight=1e12)
    flat.fit(data)
    Nv = _columns(data.val, EXPRESSIONS[0])[0]
    assert np.allclose(flat.predict(Nv, EXPRESSIONS[0]) - Nv, (E - N).mean(0), atol=1e-9)
    # target is not used
    assert np.array_equal(flat.predict(Nv, EXPRESSIONS[0], target=Nv), flat.predict(Nv, EXPRESSIONS[0]))


def test_parameters_and_inputs_are_checked(data):
    with pytest.raises(RecipeError, match="ridge_weight"):
        RidgeBlendshapes(ridge_weight=-1.0)
    with pytest.raises(RecipeError, match="n_components"):
        RidgeBlendshapes(n_components=0)
    with pytest.raises(RecipeError, match="at most 6"):  # 7 training neutrals
        RidgeBlendshapes(n_components=7).check_data(data)
    m = RidgeBlendshapes(n_components=2, expressions=[EXPRESSIONS[1]])
    m.fit(data)
    assert m.expressions == [EXPRESSIONS[1]]
    N = _columns(data.val, EXPRESSIONS[0])[0]
    with pytest.raises(DataError, match="not trained for expression"):
        m.predict(N, EXPRESSIONS[0])
    with pytest.raises(DataError, match="neutrals of shape"):
        m.predict(N[:, :10], EXPRESSIONS[1])


RECIPE = """
task: blendshapes
seed: 0
dataset: {name: synthetic-heads, n_vertices: 300, n_subjects: 12, shapes: [neutral, mouth-wide, face-compression]}
split: {ratios: [0.6, 0.2, 0.2]}
models:
  ridge: {name: ridge-bs, n_components: 5, ridge_weight: 1.0}
  dt: {name: dt}
metrics: [l1, l2]
renders: 0
"""


def test_ridge_bs_in_a_blendshapes_recipe_beside_dt(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "ridge.yaml", RECIPE, monkeypatch)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for e in EXPRESSIONS:
        rows = metrics["blendshapes"][e]
        assert {"ridge", "dt"} <= set(rows)
        assert all(np.isfinite(rows[r]["l1"]["mean"]) and rows[r]["l1"]["mean"] > 0 for r in ("ridge", "dt"))
    run = open_run(run_dir)
    model = run.model("ridge")   # reopened from models/ridge.safetensors
    assert isinstance(model, BlendshapeModel) and model.expressions == EXPRESSIONS
    assert "ridge" in (run_dir / "report.md").read_text()
