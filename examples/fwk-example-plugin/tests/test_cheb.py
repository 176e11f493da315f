"""The example conv passes fwk's conv contract suite and trains inside ae, vae (fully
convolutional too) and dsm from a recipe, as any third-party conv should."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import GenerativeModel
from fwk.testing.conv import ConvContract
from fwk.testing.sampler import two_components
from fwk_example_plugin.cheb import ChebConv
from recipe_runs import assert_tested, assert_trained, run_recipe, tiny_recipe


class TestChebContract(ConvContract):
    component = ChebConv
    params = {"k": 3}


class TestChebOnGraphLevelsContract(ConvContract):
    component = ChebConv  # levels without faces (a connectivity-only sampler)
    sampler = ("simple", {"levels": 2})


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("conv", "cheb")
    assert e.component is ChebConv and e.plugin == "example-cheb"


@pytest.mark.parametrize("k", [1, 2, 4])
def test_cheb_matches_a_dense_chebyshev_recursion(k):
    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    lv = h.levels[1]
    torch.manual_seed(0)
    conv = ChebConv(3, 5, h, 1, k=k)
    with torch.no_grad():
        conv.bias.normal_()
    A = np.zeros((lv.n_vertices, lv.n_vertices))
    A[lv.edges[:, 0], lv.edges[:, 1]] = A[lv.edges[:, 1], lv.edges[:, 0]] = 1.0
    d = A.sum(1)
    L = np.eye(len(A)) - A / np.sqrt(np.outer(d, d))      # normalised Laplacian
    Ls = 2 * L / 2.0 - np.eye(len(A))                     # scaled with lambda_max = 2
    x = np.random.default_rng(1).normal(size=(2, lv.n_vertices, 3))
    T = [x, np.einsum("ij,bjc->bic", Ls, x)]
    while len(T) < k:
        T.append(2 * np.einsum("ij,bjc->bic", Ls, T[-1]) - T[-2])
    W = conv.weight.detach().double().numpy()
    ref = sum(T[i] @ W[i] for i in range(k)) + conv.bias.detach().double().numpy()
    y = conv(torch.as_tensor(x, dtype=torch.float32)).detach().double().numpy()
    assert np.allclose(y, ref, atol=1e-5)
    assert sp.issparse(h.down[0])


RECIPE = tiny_recipe("""
ae: {name: ae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
vae: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
vae-fc: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: simple, levels: 2},
         fully_convolutional: true}
dsm: {name: dsm, k: 30, network: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8,
                                  sampler: {name: quadric, factors: [4, 4]}}}
""")


def test_cheb_trains_in_ae_vae_fully_convolutional_vae_and_dsm(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "cheb.yaml", RECIPE, monkeypatch)
    metrics = assert_tested(run_dir, {"ae", "vae", "vae-fc", "dsm"}, only=True)
    assert_trained(run_dir, metrics, epochs=2)  # two epochs trained
    run = open_run(run_dir)  # the trained models reopen from the run directory
    for label in metrics:
        model = run.model(label)
        assert isinstance(model, GenerativeModel)
        S = model.sample(2, seed=0)
        assert S.ndim == 3 and S.shape[0] == 2 and np.isfinite(S).all()
