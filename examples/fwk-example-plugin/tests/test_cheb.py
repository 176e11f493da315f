"""The example conv passes fwk's conv contract suite and trains inside ae, vae (fully
convolutional too) and dsm from a recipe, as any third-party conv should."""
import json

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from fwk.cache import Cache
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import GenerativeModel
from fwk.runs import execute
from fwk.testing.conv import ConvContract
from fwk.testing.sampler import two_components
from fwk_example_plugin.cheb import ChebConv


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


RECIPE = """
task: reconstruct
seed: 0
dataset: {name: synthetic-heads, n_vertices: 300, n_subjects: 16}
split: {ratios: [0.7, 0.1, 0.2]}
train: {epochs: 2, batch_size: 8, lr: 1.0e-3, kl_weight: 1.0e-6}
models:
  ae: {name: ae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
  vae: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
  vae-fc: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8, sampler: {name: simple, levels: 2},
           fully_convolutional: true}
  dsm: {name: dsm, k: 30, network: {name: vae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8,
                                    sampler: {name: quadric, factors: [4, 4]}}}
metrics: [l1]
renders: 0
"""


def test_cheb_trains_in_ae_vae_fully_convolutional_vae_and_dsm(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    recipe = tmp_path / "cheb.yaml"
    recipe.write_text(RECIPE)
    run_dir = execute(str(recipe), runs_dir=str(tmp_path / "runs"), quiet=True, cache=Cache(tmp_path / "cache"))
    metrics = json.loads((run_dir / "metrics.json").read_text())["models"]
    assert set(metrics) == {"ae", "vae", "vae-fc", "dsm"}
    for label, m in metrics.items():
        assert np.isfinite(m["test"]["l1"]["mean"]) and m["test"]["l1"]["mean"] > 0, label
        (events,) = {p.parent for p in (run_dir / "tb" / label).rglob("events.*")}
        ea = EventAccumulator(str(events))
        ea.Reload()
        val = [t for t in ea.Tags()["scalars"] if t.startswith("val_loss")]
        assert val and all(len(ea.Scalars(t)) == 2 and np.isfinite([e.value for e in ea.Scalars(t)]).all()
                           for t in val), label  # two epochs trained
    run = open_run(run_dir)  # the trained models reopen from the run directory
    for label in metrics:
        model = run.model(label)
        assert isinstance(model, GenerativeModel)
        S = model.sample(2, seed=0)
        assert S.ndim == 3 and S.shape[0] == 2 and np.isfinite(S).all()
