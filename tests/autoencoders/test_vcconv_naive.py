"""vcconv (strided and transposed, with and without the residual) against the naive per-vertex sum."""
import pytest
import torch

from fwk.plugins import get_registry
from fwk.testing.sampler import two_components

REG = get_registry()


def _naive(conv, x, idx, mask):
    b, n_out = x.shape[0], idx.shape[0]
    y = conv.bias.expand(b, n_out, -1).clone()
    W = torch.einsum("nkm,mco->nkco", conv.coef, conv.basis)
    for i in range(n_out):
        for k in range(idx.shape[1]):
            if mask[i, k]:
                y[:, i] += x[:, idx[i, k]] @ W[i, k]
    return y


@pytest.mark.parametrize("mode,c_in,c_out", [("down", 3, 12), ("down", 12, 2), ("up", 12, 3), ("up", 2, 12)])
@pytest.mark.parametrize("residual", [None, 0.5])
@pytest.mark.parametrize("order", ["sum", "kernel", "auto"])
def test_vcconv_matches_the_naive_sum(mode, c_in, c_out, residual, order):
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    torch.manual_seed(0)
    conv = VC(c_in, c_out, h, 0, weight_num=5, mode=mode, residual_rate=residual, order=order)
    with torch.no_grad():
        conv.bias.normal_()
        if residual is not None:
            conv.res_w.uniform_(0.1, 2.0)
    x = torch.randn(2, conv.n_in, c_in)
    lv = h.levels[1] if mode == "down" else h.levels[0]
    nb = lv.pool if mode == "down" else lv.unpool
    idx, mask = nb.index, nb.mask
    expect = _naive(conv, x, idx, mask)
    if residual is not None:
        w = torch.as_tensor(mask, dtype=torch.float32) * conv.res_w.abs()
        res = torch.einsum("nk,bnkc->bnc", w / w.sum(1, keepdim=True), x[:, torch.as_tensor(idx)])
        if conv.res_lin is not None:
            res = conv.res_lin(res)
        expect = 0.5 ** 0.5 * expect + 0.5 ** 0.5 * res
    assert torch.allclose(conv(x), expect, atol=1e-4)


def test_vcconv_orders_agree_in_value_and_gradient():
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    torch.manual_seed(1)
    conv = VC(6, 4, h, 0, weight_num=7, mode="up", residual_rate=0.5)
    x = torch.randn(3, conv.n_in, 6)
    grads = []
    for order in ("sum", "kernel"):
        conv.order = order
        conv.zero_grad()
        y = conv(x)
        (y ** 2).sum().backward()
        grads.append((y.detach(), [p.grad.clone() for p in conv.parameters()]))
    assert torch.allclose(grads[0][0], grads[1][0], atol=1e-5)
    for a, b in zip(grads[0][1], grads[1][1]):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
