"""The example model linear-net passes fwk's network-factory contract suite (variational or not),
the reconstruction and generative suites as a model of its own, computes exactly its affine maps,
and trains as the ``network:`` of dsm from a recipe."""
import numpy as np
import pytest
import torch

from fwk.errors import RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import BandModel, NetworkFactory
from fwk.testing.blendshapes import BlendshapeModelContract
from fwk.testing.generative import GenerativeModelContract
from fwk.testing.model import ModelContract, tiny_fit_data
from fwk.testing.network import NetworkFactoryContract
from fwk_example_plugin.linear_net import LinearNet
from recipe_runs import assert_tested, run_recipe, tiny_recipe


class TestLinearVAENetworks(NetworkFactoryContract):
    component = LinearNet
    params = {"latent": 6}


class TestLinearAENetworks(NetworkFactoryContract):
    component = LinearNet
    params = {"latent": 6, "variational": False}


class TestLinearNetContract(ModelContract):
    component = LinearNet
    params = {"latent": 6}


class TestLinearNetGenerative(GenerativeModelContract):
    component = LinearNet
    params = {"latent": 6, "variational": False}


class TestConditionalPBOnLinearNets(BlendshapeModelContract):
    """pb borrows the networks; conditional: its decoders read a foreign code (latent + one-hot: latent_in)."""
    component = get_registry().get("model", "pb")  # by role through the registry, never an import of the plugin
    params = {"network": {"name": "linear-net", "latent": 4}, "conditional": True}
    # conditional pb's predict_all decodes every expression in one batch (pb.predict_many): its
    # products have other shapes than one expression's and may round differently (1e-8 measured on
    # an AVX-512 EPYC, bit-equal elsewhere); everything else stays bit-for-bit
    batches_expressions = True


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("model", "linear-net")
    assert e.component is LinearNet and e.plugin == "example-linear-net"


@pytest.fixture(scope="module")
def template():
    return tiny_fit_data(n_subjects=4).template


def test_encoder_and_decoder_are_the_affine_maps(template):
    n = template.n_vertices
    torch.manual_seed(0)
    m = LinearNet(latent=5)
    enc, dec = m.build_encoder(template, 3), m.build_decoder(template, 3)
    x = torch.randn(2, n, 3, dtype=torch.float64)
    enc, dec = enc.double(), dec.double()
    mu, logvar = enc(x)
    f = x.numpy().reshape(2, -1)                       # vertex-major: entry 3 v + j is channel j of vertex v
    assert np.allclose(mu.detach().numpy(), f @ enc.mu.weight.detach().numpy().T + enc.mu.bias.detach().numpy())
    assert np.allclose(logvar.detach().numpy(),
                       f @ enc.logvar.weight.detach().numpy().T + enc.logvar.bias.detach().numpy())
    z = np.random.default_rng(0).normal(size=(2, 5))
    y = dec(torch.as_tensor(z)).detach().numpy()
    ref = z @ dec.fc.weight.detach().numpy().T + dec.fc.bias.detach().numpy()
    assert np.allclose(y, ref.reshape(2, n, 3))
    # non-variational: (mu, None); latent_parts and latent_in read d entries through the one layer
    ae = LinearNet(latent=5, variational=False)
    assert ae.build_encoder(template, 3)(x.float())[1] is None
    assert ae.build_decoder(template, 9, latent_parts=[5, 5, 5]).fc.in_features == 15
    assert ae.build_decoder(template, 9, latent_in=12).fc.in_features == 12
    with pytest.raises(RecipeError, match="not both"):
        ae.build_decoder(template, 3, latent_in=12, latent_parts=[5])


def test_parameters_are_checked():
    with pytest.raises(RecipeError, match="latent"):
        LinearNet(latent=0)
    with pytest.raises(RecipeError, match="kl_weight"):
        LinearNet(kl_weight=-1.0)
    assert isinstance(LinearNet(), NetworkFactory) and LinearNet(variational=False).variational is False


RECIPE = tiny_recipe("""
dsm-linear: {name: dsm, k: 30, network: {name: linear-net, latent: 8}}
linear: {name: linear-net, latent: 8, variational: false}
""")


def test_linear_net_as_the_network_of_dsm(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "linear.yaml", RECIPE, monkeypatch)
    assert_tested(run_dir, ("dsm-linear", "linear"))
    dsm = open_run(run_dir).model("dsm-linear")   # the borrowed networks reload from the run directory
    assert isinstance(dsm, BandModel) and dsm.latent_size == 16  # two bands x latent 8
    S = dsm.sample(2, seed=0)
    assert S.ndim == 3 and S.shape[0] == 2 and np.isfinite(S).all()
