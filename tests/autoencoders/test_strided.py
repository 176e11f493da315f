"""Strided / transposed steps of the fully convolutional layouts: a conv with the strided role is
used as it is, any other conv is composed with the sampler's pooling (PooledConv), here checked
against a naive dense computation of the thesis's block (4.4.3; Zhou et al.'s graphAE.py):
y = sqrt(1 - r) act(conv(x)) + sqrt(r) res(x), the activation on the conv branch only."""
import math

import pytest
import torch

from fwk.plugins import get_registry
from fwk.recipes import make_spec
from fwk.testing.sampler import two_components
from fwk_autoencoder.strided import PooledConv, strided_conv

REG = get_registry()


def _conv(value):
    return make_spec("conv", value, "conv", REG)


def _naive_spiralpp(conv, x):
    """x'_i = W [x_{s_1} || ... || x_{s_L}] + b, vertex by vertex."""
    idx = conv.index.reshape(x.shape[1], conv.length)
    out = torch.empty(x.shape[0], x.shape[1], conv.layer.out_features)
    for i in range(x.shape[1]):
        out[:, i] = x[:, idx[i]].reshape(x.shape[0], -1) @ conv.layer.weight.T + conv.layer.bias
    return out


def _elu(t):
    """ELU(t) = t for t > 0, exp(t) - 1 otherwise (alpha 1), written out."""
    return torch.where(t > 0, t, torch.exp(t) - 1)


@pytest.mark.parametrize("mode", ["down", "up"])
@pytest.mark.parametrize("residual", [None, 0.3])
@pytest.mark.parametrize("c_in,c_out", [(3, 7), (5, 5)])
@pytest.mark.parametrize("act", [None, "elu"])
def test_pooled_conv_matches_a_dense_computation(mode, residual, c_in, c_out, act):
    h = REG.get("sampler", "quadric")(factors=[4, 4]).build(two_components())
    level = 0
    torch.manual_seed(0)
    m = PooledConv(_conv("spiral++"), c_in, c_out, h, level, mode, residual, torch.nn.ELU() if act else None)
    with torch.no_grad():
        m.conv.layer.bias.normal_()
    P = torch.as_tensor((h.down[level] if mode == "down" else h.up[level]).toarray(), dtype=torch.float32)
    x = torch.randn(2, P.shape[1], c_in)
    p = torch.einsum("mn,bnc->bmc", P, x)                          # dense pooling
    y = _naive_spiralpp(m.conv, p)                                  # the conv on the new level
    if act:
        y = _elu(y)                                                 # on the conv branch, before the mix
    if residual is not None:
        R = p @ m.res_lin.weight.T if c_in != c_out else p
        y = math.sqrt(1 - residual) * y + math.sqrt(residual) * R  # and nothing after it
    assert torch.allclose(m(x), y, atol=1e-5)
    if act and residual is not None:  # the old order, ELU after the mix, is a different function
        old = _elu(math.sqrt(1 - residual) * _naive_spiralpp(m.conv, p) + math.sqrt(residual) * (
            p @ m.res_lin.weight.T if c_in != c_out else p))
        assert not torch.allclose(m(x), old, atol=1e-3)
    assert m.conv.index.numel() == h.levels[level + 1 if mode == "down" else level].n_vertices * m.conv.length
    assert (m.res_lin is None) == (residual is None or c_in == c_out)


def test_strided_conv_picks_by_role():
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    vc = strided_conv(_conv({"name": "vcconv", "weight_num": 4}), 3, 4, h, 0, "down", 0.5)
    assert type(vc) is REG.get("conv", "vcconv") and vc.n_out == h.levels[1].n_vertices
    lsa = strided_conv(_conv("lsa"), 3, 4, h, 0, "up", 0.5)
    assert isinstance(lsa, PooledConv) and type(lsa.conv) is REG.get("conv", "lsa")


def test_pooled_conv_reset_parameters_is_seeded():
    h = REG.get("sampler", "quadric")(factors=[4]).build(two_components())
    m = PooledConv(_conv("lsa"), 3, 6, h, 0, "down", 0.5)
    states = []
    for _ in range(2):
        torch.manual_seed(4)
        m.reset_parameters()
        states.append([p.detach().clone() for p in m.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*states))


@pytest.mark.parametrize("conv", ["spiral++", "lsa", "feast"])
def test_fully_convolutional_ae_with_a_plain_conv(conv):
    """Before the strided role was declared, these failed with a TypeError on mode=."""
    from fwk.testing.model import tiny_fit_data

    t = tiny_fit_data(n_subjects=4).template
    m = make_spec("model", {"name": "vae", "conv": conv, "sampler": {"name": "quadric", "factors": [4, 4]},
                            "channels": [8, 8], "latent": 6, "fully_convolutional": True}, "model", REG).build()
    enc, dec = m.build_encoder(t, 3), m.build_decoder(t, 3)
    assert all(isinstance(c, PooledConv) for c in [*enc.convs, *dec.convs])
    mu, logvar = enc(torch.randn(2, t.n_vertices, 3))
    assert mu.shape == logvar.shape == (2, 6)
    assert dec(mu).shape == (2, t.n_vertices, 3)


def _naive_network(convs, x, last_free=True):
    """A stack of PooledConvs evaluated block by block from their parts: pool (dense), the conv
    (checked against loops above), ELU on every block but the last, residual mix."""
    n = len(convs)
    for i, m in enumerate(convs):
        p = sparse_dense(m.pool) @ x
        y = m.conv(p)
        if i < n - 1 or not last_free:
            y = _elu(y)
        if m.r is not None:
            y = math.sqrt(1 - m.r) * y + math.sqrt(m.r) * (p @ m.res_lin.weight.T if m.res_lin is not None else p)
        x = y
    return x


def sparse_dense(M):
    return M.to_dense() if M.is_sparse else M


@pytest.mark.parametrize("layout", [{"fully_convolutional": True, "latent": 6},
                                    {"latent_vertices": 3, "conv": "lsa", "sampler": {"name": "simple", "levels": 2}}])
def test_networks_put_the_elu_on_the_conv_branch_and_none_on_the_last_block(layout):
    """Encoder and decoder of the fully convolutional layouts against the block-by-block naive
    computation: y = sqrt(1 - r) ELU(conv(x)) + sqrt(r) res(x), the last block without ELU."""
    from fwk.testing.model import tiny_fit_data

    t = tiny_fit_data(n_subjects=4).template
    spec = {"name": "ae", "conv": "spiral++", "sampler": {"name": "quadric", "factors": [4, 4]},
            "channels": [5, 4], "residual_rate": 0.3, **layout}
    m = make_spec("model", spec, "model", REG).build()
    torch.manual_seed(0)
    enc, dec = m.build_encoder(t, 3), m.build_decoder(t, 3)
    acts = [c.act for c in enc.convs]
    assert all(isinstance(a, torch.nn.ELU) for a in acts[:-1]) and acts[-1] is None
    acts = [c.act for c in dec.convs]
    assert all(isinstance(a, torch.nn.ELU) for a in acts[:-1]) and acts[-1] is None
    for mod in (enc, dec):
        assert not any(isinstance(x, torch.nn.ELU) for name, x in mod.named_children())  # none after a block
    x = torch.randn(2, t.n_vertices, 3)
    with torch.no_grad():
        h = _naive_network(list(enc.convs), x)
        mu, _ = enc(x)
        if "latent_vertices" in layout:
            assert torch.allclose(mu, h.flatten(1), atol=1e-5)
        else:
            assert torch.allclose(mu, enc.mu(h.flatten(1)), atol=1e-5)
        z = torch.randn(2, m.latent_size)
        x0 = dec.latent_map(z) if "latent_vertices" in layout else dec.fc(z).reshape(2, dec.n_last, dec.c_last)
        assert torch.allclose(dec(z), _naive_network(list(dec.convs), x0), atol=1e-5)


@pytest.mark.parametrize("layout", [{"fully_convolutional": True, "latent": 6}, {"latent": 6},
                                    {"latent_vertices": 2, "residual_rate": 0.5}])
def test_decoders_hand_on_a_batch_major_result(layout):
    """vcconv's native kernels compute vertex-major and hand on a transposed view; every decoder (the linear one,
    the fully convolutional one, the one from latent vertices) makes its result batch-major (contiguous) so that
    the loss's elementwise operations do not run strided, with the values unchanged (the last conv's own result,
    taken before the copy); the gradient goes back to the last conv as it came."""
    from fwk.testing.model import tiny_fit_data

    t = tiny_fit_data(n_subjects=4).template
    spec = {"name": "ae", "conv": "vcconv", "sampler": {"name": "simple", "levels": 2}, "channels": [5, 4],
            "residual_rate": 0.3, **layout}
    m = make_spec("model", spec, "model", REG).build()
    torch.manual_seed(0)
    dec = m.build_decoder(t, 3)
    last = dec.convs[-1] if hasattr(dec, "convs") and not hasattr(dec, "out") else dec.out
    seen = []
    last.register_forward_hook(lambda mod, args, out: seen.append(out))
    y = dec(torch.randn(2, m.latent_size))
    # the conv's vertex-major result, transposed; or, where the native lanes end a last layer with a residual in
    # elu_mix's identity mix, already laid out batch-major (and the decoder's copy is none)
    from fwk_vcconv import native as vnative

    itself = vnative.available() and vnative.lanes() and last.r is not None and last.activation is None
    assert seen[0].is_contiguous() == itself
    assert y.shape == (2, t.n_vertices, 3) and y.is_contiguous()
    assert torch.equal(y, seen[0])
    seen[0].retain_grad()
    dy = torch.randn(y.shape)
    y.backward(dy)
    assert torch.equal(seen[0].grad, dy)
