"""ae's Encoder / Decoder fuse the pooling into a conv that plays FusedPoolingConv (spiral++):
equal in value and gradient to pooling after / up-sampling before the conv, the naive
composition; checkpoints unchanged; other convs and averaging poolings are not fused."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from fwk.graph import sparse_apply
from fwk.plugins import get_registry
from fwk.protocols import FusedPoolingConv
from fwk.recipes import make_spec
from fwk.testing.sampler import two_components
from fwk_autoencoder import selected_rows

REG = get_registry()


def _nets(conv, channels=(8, 16, 16), seed=0):
    m = make_spec("model", {"name": "ae", "conv": conv, "channels": list(channels), "latent": 8,
                            "sampler": {"name": "quadric", "factors": [4, 4, 4]}}, "model", REG).build()
    t = two_components()
    torch.manual_seed(seed)
    return m.build_encoder(t, 3), m.build_decoder(t, 3), t


def _naive(enc, dec, x):
    """The composition the fused path replaces: pool(act(conv(x))) and act(conv(U x))."""
    for conv, pool in zip(enc.convs, enc.pools):
        x = pool(enc.act(conv(x)))
    z = enc.mu(x.flatten(1))
    y = dec.fc(z).reshape(len(z), dec.n_last, dec.c_last)
    for unpool, conv in zip(dec.unpools, dec.convs):
        y = dec.act(conv(unpool(y)))
    return dec.out(y)


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_spiralpp_ae_equals_the_naive_composition_in_value_and_gradient(threads):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        enc, dec, t = _nets({"name": "spiral++", "length": 9})
        assert all(k is not None for k in enc.kept) and all(dec.fused), "spiral++ on quadric fuses every level"
        assert all(isinstance(c, FusedPoolingConv) for c in enc.convs)
        x = torch.randn(3, t.n_vertices, 3)
        params = list(enc.parameters()) + list(dec.parameters())
        y = dec(enc(x)[0])
        g = torch.randn_like(y)
        got = torch.autograd.grad((y * g).sum(), params)
        e = _naive(enc, dec, x)
        ref = torch.autograd.grad((e * g).sum(), params)
        scale = e.abs().max()
        assert (y - e).abs().max() <= 1e-5 * (1 + scale)
        for a, b in zip(got, ref):
            assert (a - b).abs().max() <= 1e-4 * (1 + b.abs().max()), "gradients equal within float32 tolerance"
    finally:
        torch.set_num_threads(before)


def test_fusion_leaves_the_checkpoint_unchanged():
    enc, dec, _ = _nets({"name": "spiral++", "length": 9})
    assert not any(k.startswith("kept_") for k in enc.state_dict()), "kept rows are derived, not stored"
    enc2, dec2, t = _nets({"name": "spiral++", "length": 9}, seed=1)
    enc2.load_state_dict(enc.state_dict())
    dec2.load_state_dict(dec.state_dict())
    x = torch.randn(2, t.n_vertices, 3)
    assert torch.equal(dec(enc(x)[0]), dec2(enc2(x)[0]))


def test_a_conv_without_the_role_is_pooled_then_convolved():
    enc, dec, t = _nets("spiral")
    assert enc.kept == [None, None, None] and dec.fused == [False, False, False]
    x = torch.randn(2, t.n_vertices, 3)
    assert torch.equal(dec(enc(x)[0]), _naive(enc, dec, x))


def test_selected_rows_against_a_loop():
    rng = np.random.default_rng(0)
    cols = rng.integers(0, 20, size=7)
    D = sp.csr_matrix((np.ones(7), (np.arange(7), cols)), shape=(7, 20))
    assert np.array_equal(selected_rows(D), cols)
    dense = D.toarray()
    assert [int(np.flatnonzero(r)[0]) for r in dense] == list(selected_rows(dense))
    averaging = D.tolil()
    averaging[0, (cols[0] + 1) % 20] = 1.0
    assert selected_rows(averaging.tocsr()) is None, "two entries in a row: an averaging pooling"
    assert selected_rows(D * 0.5) is None, "a weight other than 1 is not a selection"
    x = torch.randn(2, 20, 4)
    from fwk.graph import torch_sparse
    assert torch.equal(sparse_apply(torch_sparse(D), x), x[:, torch.from_numpy(selected_rows(D))])
