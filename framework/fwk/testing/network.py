"""NetworkFactoryContract: the network-factory role (``fwk.protocols.NetworkFactory``) that lends
a model's encoder and decoder to other models (pb, pbs and dsm take ``network:``).

Subclass it in a test module::

    from fwk.testing.network import NetworkFactoryContract

    class TestMyNetworks(NetworkFactoryContract):
        component = MyModel               # the model class
        params = {"latent": 8}            # its recipe parameters, nested components as in a recipe

The model is built as a recipe builds it (``fwk.recipes.validate_params``) and its networks are
built on the small template of ``fwk.testing.model.tiny_fit_data()``.
"""
from __future__ import annotations

import pytest
import torch

from fwk.protocols import NetworkFactory, plays
from fwk.testing import build
from fwk.runs import make_test_context
from fwk.testing.conv import assert_cuda_matches_cpu
from fwk.testing.model import tiny_fit_data


class NetworkFactoryContract:
    component: type = None
    params: dict = {}
    channels: tuple = (3, 9)  # input / output feature channels tried (e.g. euclidean, dr)

    def make(self):
        """A fresh instance, its parameters resolved as a recipe resolves them."""
        return build(self.component, self.params)

    @pytest.fixture(scope="class")
    @classmethod
    def template(cls):
        return tiny_fit_data(n_subjects=4).template

    def test_plays_the_network_factory_role(self):
        m = self.make()
        assert plays(self.component, NetworkFactory), "define latent_size, variational, build_encoder, build_decoder"
        assert isinstance(m, NetworkFactory)
        assert isinstance(m.latent_size, int) and m.latent_size > 0
        assert isinstance(m.variational, bool)

    @pytest.mark.parametrize("ci", [0, 1])
    def test_encoder_and_decoder_shapes(self, template, ci):
        c = self.channels[ci]
        m = self.make()
        enc, dec = m.build_encoder(template, c), m.build_decoder(template, c)
        assert isinstance(enc, torch.nn.Module) and isinstance(dec, torch.nn.Module)
        x = torch.randn(2, template.n_vertices, c)
        mu, logvar = enc(x)
        assert mu.shape == (2, m.latent_size)
        if m.variational:
            assert logvar is not None and logvar.shape == mu.shape, "a variational encoder returns a log-variance"
        else:
            assert logvar is None, "a non-variational encoder returns (mu, None)"
        y = dec(mu)
        assert y.shape == (2, template.n_vertices, c)
        (y.square().mean() + (logvar.square().mean() if m.variational else 0)).backward()
        assert all(p.grad is not None for p in [*enc.parameters(), *dec.parameters()] if p.requires_grad), \
            "every parameter takes part in the encode-decode pass"

    def test_decoder_takes_a_foreign_latent(self, template):
        m = self.make()
        d = m.latent_size + 5
        dec = m.build_decoder(template, 3, latent_in=d)
        assert dec(torch.randn(2, d)).shape == (2, template.n_vertices, 3)

    def test_decoder_reads_concatenated_codes(self, template):
        """``latent_parts``: the decoder of a band model reads several codes concatenated (Deep
        Spectral Meshes' [Z_low | Z_high]); every entry of every part reaches the output."""
        m = self.make()
        parts = [m.latent_size, m.latent_size]
        dec = m.build_decoder(template, 3, latent_parts=parts)
        z = torch.randn(2, sum(parts), requires_grad=True)
        y = dec(z)
        assert y.shape == (2, template.n_vertices, 3)
        y.square().sum().backward()
        assert z.grad is not None and bool((z.grad.abs().sum(0) > 0).all()), "a code entry does not reach the output"

    def test_networks_are_deterministic_for_a_seed_and_take_a_context(self, template, tmp_path):
        ctx = make_test_context(tmp_path)
        states = []
        for c in (None, ctx):
            m = self.make()
            torch.manual_seed(0)
            enc, dec = m.build_encoder(template, 3, c), m.build_decoder(template, 3, c)
            states.append({**{f"e.{k}": v for k, v in enc.state_dict().items()},
                           **{f"d.{k}": v for k, v in dec.state_dict().items()}})
        a, b = states
        assert a.keys() == b.keys()
        for k in a:
            x, y = a[k], b[k]
            if x.is_sparse:
                x, y = x.to_dense(), y.to_dense()
            assert torch.equal(x, y), k

    def test_cuda_matches_cpu_when_available(self, template):
        """On a CUDA device the encoder (its mean) and the decoder give the CPU's values and
        gradients, and run under bfloat16 autocast (``fwk.testing.conv.assert_cuda_matches_cpu``)."""
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device on this machine")
        m = self.make()
        torch.manual_seed(0)
        enc, dec = m.build_encoder(template, 3), m.build_decoder(template, 3)
        assert_cuda_matches_cpu(enc, lambda e: lambda v: e(v)[0], torch.randn(2, template.n_vertices, 3))
        assert_cuda_matches_cpu(dec, lambda d: d, torch.randn(2, m.latent_size))
