"""The example model ppca passes fwk's reconstruction and generative contract suites, matches
Tipping & Bishop's ML solution computed densely, maximises the likelihood, and runs in a
reconstruct recipe."""
import numpy as np
import pytest

from fwk.errors import RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import GenerativeModel, ReconstructionModel
from fwk.testing.generative import GenerativeModelContract
from fwk.testing.model import ModelContract, tiny_fit_data
from fwk_example_plugin.ppca import PPCA, log_likelihood
from recipe_runs import assert_tested, run_recipe, tiny_recipe


class TestPPCAContract(ModelContract):
    component = PPCA
    params = {"n_components": 5}


class TestPPCAGenerative(GenerativeModelContract):
    component = PPCA
    params = {"n_components": 5}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("model", "ppca")
    assert e.component is PPCA and e.plugin == "example-ppca"


@pytest.fixture(scope="module")
def fitted():
    data = tiny_fit_data()
    m = PPCA(n_components=4)
    m.fit(data)
    return m, data


def _dense(X, q):
    """Tipping & Bishop's ML W and sigma^2 from the dense d x d sample covariance (numpy only)."""
    mu = X.mean(0)
    S = (X - mu).T @ (X - mu) / len(X)
    lam, U = np.linalg.eigh(S)
    lam, U = lam[::-1], U[:, ::-1]
    sigma2 = lam[q:].mean()
    return mu, S, U[:, :q] * np.sqrt(lam[:q] - sigma2), sigma2


def _dense_loglik(X, mu, W, sigma2):
    C = W @ W.T + sigma2 * np.eye(len(W))
    _, logdet = np.linalg.slogdet(C)
    D = X - mu
    return -0.5 * (X.shape[1] * np.log(2 * np.pi) + logdet + np.sum(D * np.linalg.solve(C, D.T).T, axis=1))


def test_ml_solution_matches_the_dense_eigendecomposition(fitted):
    m, data = fitted
    X = data.stack("train").reshape(len(data.stack("train")), -1)
    mu, S, W, sigma2 = _dense(X, 4)
    assert np.allclose(m.mean, mu, atol=1e-12)
    assert m.sigma2 == pytest.approx(sigma2, rel=1e-8)
    assert np.allclose(m.W @ m.W.T, W @ W.T, atol=1e-10)            # W up to its rotation R
    assert np.allclose(m.eigenvalues, np.linalg.eigvalsh(S)[::-1][:4], rtol=1e-8)
    # the gradient of the log-likelihood in W, N (C^-1 S C^-1 W - C^-1 W), vanishes at the ML solution
    C = m.W @ m.W.T + m.sigma2 * np.eye(len(m.W))
    Ci_W = np.linalg.solve(C, m.W)
    assert np.allclose(np.linalg.solve(C, S @ Ci_W), Ci_W, atol=1e-8 * np.abs(Ci_W).max())


def test_likelihood_is_maximal_at_the_ml_solution(fitted):
    m, data = fitted
    P = data.stack("train")
    X = P.reshape(len(P), -1)
    ll = m.log_likelihood(P)
    assert np.allclose(ll, _dense_loglik(X, m.mean, m.W, m.sigma2), rtol=1e-9)  # Woodbury == dense
    best = ll.sum()
    rng = np.random.default_rng(0)
    scale = np.abs(m.W).max()
    for eps in (1e-1, 1e-2, 1e-3):
        for _ in range(3):
            W2 = m.W + eps * scale * rng.standard_normal(m.W.shape)
            assert log_likelihood(X, m.mean, W2, m.sigma2).sum() < best
        for f in (1 - eps, 1 + eps):
            assert log_likelihood(X, m.mean, m.W, m.sigma2 * f).sum() < best
            assert log_likelihood(X, m.mean, m.W * f, m.sigma2).sum() < best


def test_posterior_mean_and_shrinkage(fitted):
    m, data = fitted
    P = data.stack("val")
    D = P.reshape(len(P), -1) - m.mean
    M = m.W.T @ m.W + m.sigma2 * np.eye(4)
    Z = m.encode(P)
    assert np.allclose(Z, D @ m.W @ np.linalg.inv(M).T, atol=1e-12)   # M^-1 W^T (x - mu)
    # along principal direction j the reconstruction keeps (lambda_j - sigma^2) / lambda_j of x - mu
    U = m.W / np.linalg.norm(m.W, axis=0)
    R = m.reconstruct(P).reshape(len(P), -1) - m.mean
    assert np.allclose(R, (D @ U) * (1 - m.sigma2 / m.eigenvalues) @ U.T, atol=1e-12)
    # sample is W z + mu for z ~ N(0, I), no noise
    z = np.random.default_rng(7).standard_normal((2, 4))
    assert np.allclose(m.sample(2, seed=7).reshape(2, -1), m.mean + z @ m.W.T)


def test_component_count_is_checked():
    data = tiny_fit_data()
    with pytest.raises(RecipeError, match="n_components"):
        PPCA(n_components=0)
    with pytest.raises(RecipeError, match="at most 11"):  # 13 training meshes: q <= m - 2
        PPCA(n_components=12).check_data(data)
    m = PPCA()
    m.fit(data)
    assert m.latent_size == 11 and m.sigma2 > 0


RECIPE = tiny_recipe("""
ppca: {name: ppca, n_components: 6}
pca: {name: pca, n_components: 6}
""", epochs=None)  # fitted, not trained


def test_ppca_in_a_reconstruct_recipe(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "ppca.yaml", RECIPE, monkeypatch)
    assert_tested(run_dir, ("ppca", "pca"))
    model = open_run(run_dir).model("ppca")
    assert isinstance(model, ReconstructionModel) and isinstance(model, GenerativeModel)
    S = model.sample(2, seed=0)
    assert S.shape == (2, model.n_vertices, 3) and np.isfinite(S).all()
