"""The example model band-pca passes fwk's reconstruction and band-model contract suites, its
bands sum back to the mesh, each band's reconstruction is a numpy PCA of that band, and it runs in
a reconstruct recipe."""
import numpy as np
import pytest

from fwk.cache import Cache
from fwk.errors import RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import BandModel
from fwk.recipes import make_spec
from fwk.runs import make_test_context
from fwk.testing.generative import BandModelContract
from fwk.testing.model import ModelContract, tiny_fit_data
from fwk_example_plugin.band_pca import BandPCA
from recipe_runs import assert_tested, run_recipe, tiny_recipe

SPECTRAL = {"name": "spectral", "k": 20}


class TestBandPCAContract(ModelContract):
    component = BandPCA
    params = {"assembler": SPECTRAL, "n_components": [4, 3]}


class TestBandPCABands(BandModelContract):
    component = BandPCA
    params = {"assembler": SPECTRAL, "n_components": [4, 3]}


class TestThreeBands(BandModelContract):
    component = BandPCA
    params = {"assembler": {"name": "spectral", "k": [10, 40]}, "n_components": 3}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("model", "band-pca")
    assert e.component is BandPCA and e.plugin == "example-band-pca"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    data = tiny_fit_data()
    m = BandPCA(assembler=SPECTRAL, n_components=[4, 3])
    m.fit(data, make_test_context(tmp_path_factory.mktemp("band-pca")))
    return m, data


def test_bands_sum_back_to_the_mesh(fitted, tmp_path):
    m, data = fitted
    P = data.stack("val")
    bands = m.split(P)
    assert m.band_names == ["low", "high"] and len(bands) == 2
    assert np.allclose(sum(b - m.mean for b in bands) + m.mean, P, atol=1e-10)
    # the bands are the spectral assembler's, built and fitted here independently
    a = make_spec("assembler", SPECTRAL, "assembler").build()
    a.fit(data.template, data.stack("train").mean(0), cache=Cache(tmp_path / "cache"))
    for x, y in zip(a.split(P), bands):
        assert np.allclose(x, y, atol=1e-10)


def test_each_band_is_reconstructed_by_its_own_pca(fitted):
    m, data = fitted
    T, P = data.stack("train"), data.stack("val")
    mean = T.mean(0)
    Z = m.encode(P)
    parts = m.decode_bands(Z)
    expected = []
    for j, q in enumerate([4, 3]):
        X = (m.split(T)[j] - mean).reshape(len(T), -1)          # numpy PCA of band j of the training set
        mu = X.mean(0)
        _, s, Vt = np.linalg.svd(X - mu, full_matrices=False)
        V = Vt[:q]
        Y = (m.split(P)[j] - mean).reshape(len(P), -1)
        ref = mean + (mu + (Y - mu) @ V.T @ V).reshape(P.shape)
        assert np.allclose(parts[j], ref, atol=1e-10), m.band_names[j]
        # the band's code is whitened: unit variance on the training meshes
        Zt = m.encode(T)[:, m.latent_slice(j)]
        assert np.allclose(Zt.std(0, ddof=1), 1, atol=1e-8)
        assert np.allclose(np.abs(Z[:, m.latent_slice(j)]), np.abs((Y - mu) @ V.T / (s[:q] / np.sqrt(len(T) - 1))),
                           atol=1e-8)
        expected.append(ref)
    # the assembly adds the bands' reconstructions back: the displacements sum
    assert np.allclose(m.reconstruct(P), sum(r - mean for r in expected) + mean, atol=1e-10)


def test_parameters_are_checked(tmp_path):
    ctx = make_test_context(tmp_path)  # the assembler's eigenbasis cached in tmp_path
    with pytest.raises(RecipeError, match="n_components"):
        BandPCA(n_components=0)
    with pytest.raises(RecipeError, match="band_names"):
        BandPCA(band_names=["a", "a"])
    data = tiny_fit_data()
    with pytest.raises(RecipeError, match="at most 12"):
        BandPCA(assembler=SPECTRAL, n_components=13).check_data(data)
    with pytest.raises(RecipeError, match="3 given, the assembler makes 2 bands"):
        BandPCA(assembler=SPECTRAL, n_components=[2, 2, 2]).fit(data, ctx)
    with pytest.raises(RecipeError, match=r"^assembler\.k: .*exceeds"):  # spectral's own k: 500 > n
        BandPCA(n_components=2).fit(data, ctx)


RECIPE = tiny_recipe("""
band-pca: {name: band-pca, assembler: {name: spectral, k: 30}, n_components: [6, 4]}
pca: {name: pca, n_components: 10}
""", epochs=None)  # fitted, not trained


def test_band_pca_in_a_reconstruct_recipe(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "band-pca.yaml", RECIPE, monkeypatch)
    assert_tested(run_dir, ("band-pca", "pca"))
    model = open_run(run_dir).model("band-pca")   # reopened from models/band-pca.safetensors
    assert isinstance(model, BandModel) and model.latent_size == 10
    assert model.latent_slice("high") == slice(6, 10)
    S = model.sample(2, seed=0)
    assert S.shape == (2, model.mean.shape[0], 3) and np.isfinite(S).all()
