"""Decoders that read several codes as one latent map (``build_decoder(..., latent_parts=...)``,
Deep Spectral Meshes' Z, thesis 4.4.2 and figure 4.1): the first transposed convolution reads the
(b, n_latent, sum of channels) map, channels concatenated per latent vertex, with no dense layer;
an edit of one latent vertex changes the first layer's output only inside that vertex's support."""
import pytest
import torch

from fwk.errors import RecipeError
from fwk.plugins import get_registry
from fwk.recipes import make_spec
from fwk.testing.model import tiny_fit_data

REG = get_registry()


def _vae(**kw):
    spec = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 6}, "sampler": {"name": "simple", "levels": 2},
            "channels": [8, 8, 4], "latent_vertices": 5, **kw}
    return make_spec("model", spec, "model", REG).build()


@pytest.fixture(scope="module")
def template():
    return tiny_fit_data(n_subjects=4).template


def _first_input(dec, z):
    seen = []
    h = dec.convs[0].register_forward_pre_hook(lambda mod, args: seen.append(args[0].detach().clone()))
    try:
        out = dec(z)
    finally:
        h.remove()
    return seen[0], out


def test_parts_are_read_as_one_map_without_a_dense_layer(template):
    m = _vae()
    torch.manual_seed(0)
    dec = m.build_decoder(template, 3, latent_parts=[20, 10])  # 5 latent vertices x (4 + 2) channels
    assert not any(isinstance(x, torch.nn.Linear) and x.in_features == 30 for x in dec.modules())
    assert dec.fc is None and dec.map_channels == 6
    z0, z1 = torch.randn(2, 20), torch.randn(2, 10)
    x, out = _first_input(dec, torch.cat([z0, z1], 1))
    assert x.shape == (2, 5, 6) and out.shape == (2, template.n_vertices, 3)
    assert torch.equal(x, torch.cat([z0.reshape(2, 5, 4), z1.reshape(2, 5, 2)], 2))  # row v: every code at vertex v
    assert torch.equal(dec(x), out)  # the map itself is accepted too


def test_own_code_is_the_same_map(template):
    m = _vae()
    dec = m.build_decoder(template, 3)
    z = torch.randn(3, m.latent_size)
    x, _ = _first_input(dec, z)
    assert x.shape == (3, 5, 4) and torch.equal(x, z.reshape(3, 5, 4))
    enc = m.build_encoder(template, 3)
    mu, _ = enc(torch.randn(2, template.n_vertices, 3))
    assert dec(mu).shape == (2, template.n_vertices, 3)


def test_an_edit_of_one_latent_vertex_stays_in_its_support(template):
    m = _vae()
    torch.manual_seed(1)
    dec = m.build_decoder(template, 3, latent_parts=[20, 20])
    first = dec.convs[0]
    h = m.hierarchy
    L = len(h.levels) - 1
    nb = h.levels[L - 1].unpool  # the transposed convolution's support: latent vertex -> vertices of level L - 1
    z = torch.randn(1, 40)
    with torch.no_grad():
        x = dec.latent_map(z)
        y = first(x)
        for v in range(5):
            for part in (0, 1):  # one band's channels, then the other's, at latent vertex v
                x2 = x.clone()
                x2[0, v, 4 * part:4 * part + 4] += torch.randn(4)
                changed = (first(x2) - y).abs().amax(dim=(0, 2)) > 0
                support = torch.as_tensor([(nb.index[i][nb.mask[i] > 0] == v).any() for i in range(len(nb.index))])
                assert changed.any() and not (changed & ~support).any(), (v, part)


def test_flat_codes_and_bad_parts(template):
    flat = make_spec("model", {"name": "vae", "channels": [8], "latent": 4,
                               "sampler": {"name": "quadric", "factors": [4]}}, "model", REG).build()
    dec = flat.build_decoder(template, 3, latent_parts=[4, 4])  # one latent vertex: its own linear layer
    assert dec.fc.in_features == 8 and dec(torch.randn(2, 8)).shape == (2, template.n_vertices, 3)
    m = _vae()
    with pytest.raises(RecipeError, match="latent_parts"):
        m.build_decoder(template, 3, latent_parts=[20, 7])
    with pytest.raises(RecipeError, match="not both"):
        m.build_decoder(template, 3, latent_in=20, latent_parts=[20])
