"""vcconv (strided and transposed, with and without the residual and the activation) against the
naive per-vertex sum, in value and in gradient (every parameter and the input)."""
import math

import numpy as np

import pytest
import torch

from fwk.plugins import get_registry
from fwk.testing.sampler import two_components

REG = get_registry()


@pytest.fixture(autouse=True, params=["native", "torch"])
def evaluation(request, monkeypatch):
    """Every test runs on the native kernels (``fwk_vcconv.native``) and on the torch code. On the
    native kernels every product with the basis takes ``tall_product`` (which, by default, only
    products of 4,096 rows or more do; these meshes are smaller)."""
    from fwk_vcconv import native

    if request.param == "torch":
        monkeypatch.setenv("FWK_VCCONV_NATIVE", "0")
    elif not native.available():
        pytest.skip(f"native kernels unavailable: {native.failed()}")
    else:
        monkeypatch.setattr(native, "TALL_MIN_ROWS", 0)
    return request.param


def _naive_conv(conv, x, idx, mask):
    """y_i = b + sum_{j in N(i)} sum_m A_ijm B_m^T x_j, one output vertex at a time."""
    A = conv.padded(conv.coef)  # (n_out, K, M), zero at the padding
    rows = []
    for i in range(idx.shape[0]):
        ks = [k for k in range(idx.shape[1]) if mask[i, k]]
        js = [int(idx[i, k]) for k in ks]
        W = torch.einsum("km,mco->kco", A[i, ks], conv.basis)  # W_ij = sum_m A_ijm B_m
        rows.append(conv.bias + torch.einsum("bkc,kco->bo", x[:, js], W))
    return torch.stack(rows, 1)


def _naive_residual(conv, x, idx, mask):
    """res_i = R sum_j w~_ij x_j with w~_ij = |w_ij| / sum_j |w_ij| (the identity for mode same)."""
    if conv.res_w is None:
        res = x
    else:
        rows = []
        for i in range(idx.shape[0]):
            ks = [k for k in range(idx.shape[1]) if mask[i, k]]
            w = conv.padded(conv.res_w)[i, ks].abs()
            rows.append(torch.einsum("k,bkc->bc", w / w.sum(), x[:, [int(idx[i, k]) for k in ks]]))
        res = torch.stack(rows, 1)
    return conv.res_lin(res) if conv.res_lin is not None else res


def _naive(conv, x, idx, mask, act, r):
    y = _naive_conv(conv, x, idx, mask)
    y = act(y) if act is not None else y
    if r is None:
        return y
    return math.sqrt(1 - r) * y + math.sqrt(r) * _naive_residual(conv, x, idx, mask)


def close(a, e, tol=1e-5):
    """Equal within float32 rounding of sums: |a - e| <= tol (1 + max |e|) everywhere."""
    return a.shape == e.shape and bool((a - e).abs().max() <= tol * (1 + e.abs().max()))


def _support(h, mode, level=1):
    lv = h.levels[level + 1] if mode == "down" else h.levels[level]
    nb = lv.pool if mode == "down" else lv.unpool
    return nb.index, nb.mask


ORDERS = ["sum", "kernel", "basis", "auto"]


@pytest.mark.parametrize("mode,c_in,c_out", [("down", 3, 12), ("down", 12, 2), ("up", 12, 3), ("up", 2, 12),
                                             ("down", 6, 6), ("up", 6, 6)])
@pytest.mark.parametrize("residual,act", [(None, None), (None, "elu"), (0.5, "elu"), (0.3, None)])
@pytest.mark.parametrize("order", ORDERS)
def test_vcconv_matches_the_naive_sum_in_value_and_gradient(mode, c_in, c_out, residual, act, order):
    h = REG.get("sampler", "simple")(levels=3).build(two_components())
    VC = REG.get("conv", "vcconv")
    torch.manual_seed(0)
    activation = torch.nn.ELU() if act else None
    # levels 1 <-> 2 of the two-component test mesh (324 <-> 84 vertices)
    conv = VC(c_in, c_out, h, 1, weight_num=5, mode=mode, residual_rate=residual, order=order, activation=activation)
    with torch.no_grad():
        conv.bias.normal_()
        if residual is not None:
            conv.res_w.uniform_(0.1, 2.0)
    idx, mask = _support(h, mode)
    x = torch.randn(2, conv.n_in, c_in, requires_grad=True)
    g = torch.randn(2, idx.shape[0], c_out)  # a random upstream gradient

    y = conv(x)
    (y * g).sum().backward()
    got = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]
    x.grad = None
    conv.zero_grad()
    expect = _naive(conv, x, idx, mask, activation, residual)
    (expect * g).sum().backward()
    ref = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]

    assert y.shape == expect.shape
    assert close(y, expect)
    names = ["x"] + [n for n, _ in conv.named_parameters()]
    for name, a, e in zip(names, got, ref):
        assert close(a, e), (name, (a - e).abs().max(), e.abs().max())


@pytest.mark.parametrize("residual", [None, 0.5])
def test_vcconv_same_mode_matches_the_naive_sum(residual):
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    for order in ORDERS:
        torch.manual_seed(3)
        conv = VC(4, 5, h, 1, weight_num=3, mode="same", residual_rate=residual, order=order,
                  activation=torch.nn.ELU())
        x = torch.randn(3, conv.n_in, 4, requires_grad=True)
        y = conv(x)
        y.square().sum().backward()
        got = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]
        x.grad = None
        conv.zero_grad()
        idx, mask = conv.index, conv.mask.bool()
        expect = _naive(conv, x, idx, mask, conv.activation, residual)
        expect.square().sum().backward()
        ref = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]
        assert close(y, expect), order
        for a, e in zip(got, ref):
            assert close(a, e), order


def test_vcconv_activation_is_on_the_conv_branch_only():
    """y = sqrt(1 - r) act(conv) + sqrt(r) res (thesis l. 1787; Zhou et al.'s graphAE.py), not act(mix)."""
    h = REG.get("sampler", "simple")(levels=3).build(two_components())
    VC = REG.get("conv", "vcconv")
    torch.manual_seed(4)
    relu = VC(3, 3, h, 1, weight_num=4, mode="down", residual_rate=0.5, activation=torch.nn.ReLU())
    plain = VC(3, 3, h, 1, weight_num=4, mode="down")
    plain.load_state_dict({k: v for k, v in relu.state_dict().items() if k in plain.state_dict()})
    x = -torch.rand(2, relu.n_in, 3) - 1.0  # all negative: the residual average is negative
    res = _naive_residual(relu, x, *_support(h, "down"))
    assert (res < 0).all()
    y = relu(x)
    expect = 0.5 ** 0.5 * torch.relu(plain(x)) + 0.5 ** 0.5 * res
    assert torch.allclose(y, expect, atol=1e-5)
    assert (y < 0).any(), "the residual is added after the activation, so the output can be negative"


def test_vcconv_orders_agree_in_value_and_gradient():
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    torch.manual_seed(1)
    conv = VC(6, 4, h, 0, weight_num=7, mode="up", residual_rate=0.5, activation=torch.nn.ELU())
    x = torch.randn(3, conv.n_in, 6)
    grads = []
    for order in ("sum", "kernel", "basis"):
        conv.order = order
        conv.zero_grad()
        y = conv(x)
        (y ** 2).sum().backward()
        grads.append((y.detach(), [p.grad.clone() for p in conv.parameters()]))
    for other in grads[1:]:
        assert close(other[0], grads[0][0])
        for a, b in zip(grads[0][1], other[1]):
            assert close(b, a)


def test_vcconv_multiply_adds_are_the_dense_products_torch_counts(evaluation):
    """``multiply_adds`` (half of auto's cost model) against torch's own count of the forward's
    dense products (mm, bmm, addmm), for every order, mode and a few widths (no residual path: the
    residual rides along as an extra coefficient, which the model leaves out). On the native
    kernels (their multiply-adds registered with the counter) ``multiply_adds(b, native_kernels=True)``:
    the same sums over the exact slots."""
    from torch.utils.flop_counter import FlopCounterMode

    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    for mode, c_in, c_out in (("down", 3, 16), ("up", 16, 3), ("same", 8, 8), ("up", 8, 3)):
        conv = VC(c_in, c_out, h, 0, weight_num=7, mode=mode)
        x = torch.randn(5, conv.n_in, c_in)
        for order in ("sum", "basis", "kernel"):
            conv.order = order
            with torch.no_grad(), FlopCounterMode(display=False) as fc:
                conv(x)
            expect = conv.multiply_adds(5, native_kernels=evaluation == "native")[order]
            assert fc.get_total_flops() == 2 * expect, (mode, c_in, c_out, order)


def test_vcconv_auto_order_weighs_memory_traffic_and_runs_under_bf16_autocast(evaluation):
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    from fwk_vcconv import FLOAT_COST

    # a decoder's last layer at the chapter 5 width (8 -> 3 channels, batch 16): the explicit kernels
    # need half the multiply-adds of the basis order, but gather every input row once per slot
    # (b c floats a slot against b c_out): auto takes the basis order, as measured on ICT-FaceKit
    conv = VC(8, 3, h, 0, weight_num=35, mode="up", residual_rate=0.5)
    macs, floats = conv.multiply_adds(16), conv.traffic(16)
    assert macs["kernel"] < macs["basis"] and floats["basis"] < floats["kernel"]
    assert conv.chosen_order(16) == "basis"
    cost = conv.costs(16)
    assert all(cost[k] == macs[k] + FLOAT_COST * floats[k] for k in cost)
    torch.manual_seed(5)
    for mode, c_in, c_out in (("down", 3, 16), ("up", 16, 3)):
        conv = VC(c_in, c_out, h, 0, weight_num=6, mode=mode, residual_rate=0.5, activation=torch.nn.ELU())
        cost = conv.costs(4, native_kernels=evaluation == "native")
        assert conv.chosen_order(4) == min(cost, key=cost.get)
        x = torch.randn(4, conv.n_in, c_in)
        y = conv(x)
        for order in ("sum", "basis", "kernel"):
            conv.order = order
            with torch.autocast("cpu", dtype=torch.bfloat16):
                y16 = conv(x)
            assert y16.shape == y.shape and torch.isfinite(y16).all()
            assert (y16.float() - y).abs().max() <= 0.05 * (1 + y.abs().max()), order
        conv.order = "auto"


def test_vcconv_state_dict_keys_are_unchanged():
    """Checkpoints written before the bucketed evaluation load: the plans are not in the state_dict."""
    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    conv = REG.get("conv", "vcconv")(3, 4, h, 0, weight_num=5, mode="down", residual_rate=0.5)
    assert set(conv.state_dict()) == {"index", "mask", "basis", "coef", "bias", "res_w", "res_lin.weight"}


def _uneven():
    """A UV sphere: its poles have 16 neighbours, every other vertex 6, so supports differ in size
    and the torch code pads them (the native kernels do not)."""
    import trimesh

    from fwk.data import Template

    m = trimesh.creation.uv_sphere(count=[10, 16])
    return Template(np.asarray(m.vertices), np.asarray(m.faces))


@pytest.mark.parametrize("mode,c_in,c_out", [("down", 3, 8), ("up", 8, 3), ("same", 4, 5)])
@pytest.mark.parametrize("order", ["sum", "basis"])
def test_vcconv_matches_the_naive_sum_on_uneven_supports(mode, c_in, c_out, order):
    h = REG.get("sampler", "simple")(levels=3).build(_uneven())
    torch.manual_seed(6)
    level = 0 if mode != "same" else 1
    conv = REG.get("conv", "vcconv")(c_in, c_out, h, level, weight_num=4, mode=mode, residual_rate=0.5,
                                      order=order, activation=torch.nn.ELU())
    assert conv._out_slots > len(conv._nat_out_src) or conv._in_slots > len(conv._nat_in_dst), "supports padded"
    with torch.no_grad():
        conv.bias.normal_()
        if conv.res_w is not None:
            conv.res_w.uniform_(0.1, 2.0)
    x = torch.randn(3, conv.n_in, c_in, requires_grad=True)
    g = torch.randn(3, conv.n_out, c_out)
    (conv(x) * g).sum().backward()
    got = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]
    y = conv(x).detach()
    x.grad = None
    conv.zero_grad()
    idx, mask = conv.index, conv.mask.bool()
    expect = _naive(conv, x, idx, mask, conv.activation, 0.5)
    (expect * g).sum().backward()
    ref = [x.grad.clone()] + [p.grad.clone() for p in conv.parameters()]
    assert close(y, expect)
    for name, a, e in zip(["x"] + [n for n, _ in conv.named_parameters()], got, ref):
        assert close(a, e), name
