"""ae and vae play the network-factory, reconstruction and generative roles."""
import numpy as np
import pytest

from fwk.plugins import get_registry
from fwk.protocols import GenerativeModel, NetworkFactory, ReconstructionModel, plays
from fwk.testing.network import NetworkFactoryContract

REG = get_registry()
AE, VAE = REG.get("model", "ae"), REG.get("model", "vae")
QUADRIC = {"name": "quadric", "factors": [4, 4]}


class TestAENetworks(NetworkFactoryContract):
    component = AE
    params = {"channels": [8, 16], "latent": 8, "sampler": QUADRIC}


class TestVAENetworks(NetworkFactoryContract):
    component = VAE
    params = {"channels": [8, 16], "latent": 8, "sampler": QUADRIC, "conv": {"name": "lsa", "basis": 4}}


class TestFullyConvolutionalVCConvNetworks(NetworkFactoryContract):
    component = VAE
    params = {"conv": {"name": "vcconv", "weight_num": 4}, "sampler": {"name": "simple", "levels": 2},
              "channels": [8, 8], "latent": 8, "fully_convolutional": True}


class TestFullyConvolutionalSpiralNetworks(NetworkFactoryContract):
    component = AE  # a conv without the strided role, composed with the sampler's pooling
    params = {"conv": "spiral++", "sampler": QUADRIC, "channels": [8, 8], "latent": 8, "fully_convolutional": True}


class TestLatentVerticesVCConvNetworks(NetworkFactoryContract):
    component = VAE  # the chapter 5 and Deep Spectral Meshes network's shape, small
    params = {"conv": {"name": "vcconv", "weight_num": 4, "radius": 2}, "residual_rate": 0.5,
              "sampler": {"name": "simple", "levels": 2, "stride": 2, "radius": 2}, "channels": [8, 8, 4],
              "latent_vertices": 5}


class TestLatentVerticesLSANetworks(NetworkFactoryContract):
    component = VAE
    params = {"conv": "lsa", "sampler": {"name": "simple", "levels": 2}, "channels": [8, 8, 4],
              "latent_vertices": 5}


def test_ae_and_vae_play_their_roles():
    for cls in (AE, VAE):
        for role in (NetworkFactory, ReconstructionModel, GenerativeModel):
            assert plays(cls, role), (cls.name, role.__name__)
    assert AE.variational is False and VAE.variational is True


def test_default_representation_is_euclidean_with_std_scaling():
    from fwk.recipes import make_spec

    m = make_spec("model", {"name": "ae"}, "model", REG).build()
    rep = m.representation.build()
    ref = REG.get("representation", m.representation.name)(scaling="std")
    X = np.random.default_rng(0).normal(size=(6, 20, 3))
    rep.fit(X, None, None)
    ref.fit(X, None, None)
    assert m.representation.params == {}
    assert np.array_equal(rep.encode(X), ref.encode(X))


@pytest.mark.parametrize("case", [TestAENetworks, TestVAENetworks, TestFullyConvolutionalVCConvNetworks,
                                  TestFullyConvolutionalSpiralNetworks, TestLatentVerticesLSANetworks])
def test_decoders_read_concatenated_codes(case):
    """build_decoder(..., latent_parts=[d, d]): two codes of this network's layout in one input
    (Deep Spectral Meshes' Z), for every layout; a latent map has no linear layer reading them."""
    import torch

    from fwk.testing.model import tiny_fit_data

    t = tiny_fit_data(n_subjects=4).template
    m = case().make()
    d = m.latent_size
    enc, dec = m.build_encoder(t, 3), m.build_decoder(t, 9, latent_parts=[d, d])
    mu, _ = enc(torch.randn(2, t.n_vertices, 3))
    assert dec(torch.cat([mu, mu], 1)).shape == (2, t.n_vertices, 9)
    if m.latent_vertices:
        assert not any(isinstance(x, torch.nn.Linear) and x.in_features == 2 * d for x in dec.modules())
