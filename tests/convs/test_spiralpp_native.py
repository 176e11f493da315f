"""spiral++'s native kernel (``fwk_spiralpp.native``) against the naive per-vertex sum in float64
and against the torch code (``GatherLinear``), in value and gradient; its thread behaviour, its
refusals and its multiply-add count. The whole conv on both paths against the loop is
``tests/convs/test_spiralpp.py``; the fused AE, ``tests/autoencoders/test_fused_pooling.py``."""
import pytest
import torch

from fwk_spiralpp import GatherLinear, native


def test_the_native_kernel_builds():
    """CI has a compiler (``.ci/run``): the kernel must build there, not fall back silently."""
    if not native.enabled():
        pytest.skip("FWK_SPIRALPP_NATIVE=0")
    assert native.available(), native.failed()


needs_native = pytest.mark.skipif(not native.available(), reason=f"native kernel unavailable: {native.failed()}")


def _naive(x, W, bias, index):
    """y[i, s] = W [x[index[i, 0], s] || ... || x[index[i, L-1], s]] + bias, vertex by vertex."""
    rows = [torch.cat([x[int(j)] for j in index[i]], -1) @ W.T for i in range(index.shape[0])]
    y = torch.stack(rows)
    return y + bias if bias is not None else y


def _problem(n_in, n_out, b, c, o, L, g, bias=True):
    x = torch.randn(n_in, b, c, generator=g)
    W = torch.randn(o, L * c, generator=g)
    bb = torch.randn(o, generator=g) if bias else None
    index = torch.randint(0, n_in, (n_out, L), generator=g)
    index[0] = 0  # a padded spiral: one vertex named L times
    return x, W, bb, index


# the block holds 64 Ki floats: (40, 16, 33) with L = 9 makes blocks of 13 vertices, the last one short
SHAPES = [(30, 30, 4, 3, 8, 9), (50, 20, 16, 8, 3, 9), (40, 64, 16, 33, 17, 9), (25, 25, 1, 1, 1, 1)]


@needs_native
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("threads", [1, 2])
def test_gather_linear_matches_the_loop_in_float64_in_value_and_gradient(shape, bias, threads, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(sum(shape))
    x, W, bb, index = _problem(*shape, g, bias=bias)
    leaves = [t.requires_grad_() for t in (x, W) + ((bb,) if bias else ())]
    y = native.gather_linear(x, W, bb if bias else x.new_empty(0), index)
    gy = torch.randn(y.shape, generator=g)
    got = torch.autograd.grad(y, leaves, gy)
    ref_leaves = [t.detach().double().requires_grad_() for t in leaves]
    e = _naive(ref_leaves[0], ref_leaves[1], ref_leaves[2] if bias else None, index)
    want = torch.autograd.grad(e, ref_leaves, gy.double())
    assert y.dtype == torch.float32 and y.shape == e.shape
    assert (y.double() - e).abs().max() <= 1e-5 * (1 + e.abs().max())
    for a, w in zip(got, want):
        assert (a.double() - w).abs().max() <= 1e-5 * (1 + w.abs().max()), (a.double() - w).abs().max()


@needs_native
@pytest.mark.parametrize("threads", [1, 2])
def test_gather_linear_agrees_with_the_torch_code_and_repeats_its_bits(threads, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(7)
    x, W, bb, index = _problem(300, 200, 8, 16, 12, 9, g)
    x.requires_grad_(), W.requires_grad_(), bb.requires_grad_()
    gy = torch.randn(200, 8, 12, generator=g)

    def run(f):
        y = f()
        return [y.detach()] + [t.clone() for t in torch.autograd.grad(y, (x, W, bb), gy)]

    nat = run(lambda: native.gather_linear(x, W, bb, index))
    tor = run(lambda: GatherLinear.apply(x, W, bb, index, GatherLinear.rows_of(index, 8), 7))
    for a, t in zip(nat, tor):
        assert (a - t).abs().max() <= 1e-5 * (1 + t.abs().max())
    again = run(lambda: native.gather_linear(x, W, bb, index))
    assert all(torch.equal(a, b) for a, b in zip(nat, again)), "same thread count, same bits"


@needs_native
def test_only_the_asked_gradients_are_computed():
    g = torch.Generator().manual_seed(3)
    x, W, bb, index = _problem(20, 20, 2, 4, 5, 9, g)
    W.requires_grad_()
    y = native.gather_linear(x, W, bb, index)
    (dW,) = torch.autograd.grad(y.sum(), (W,))
    Wd = W.detach().double().requires_grad_()
    (want,) = torch.autograd.grad(_naive(x.double(), Wd, bb.double(), index).sum(), (Wd,))
    assert (dW.double() - want).abs().max() <= 1e-5 * (1 + want.abs().max())
    assert x.grad is None and bb.grad is None


@needs_native
def test_malformed_arguments_are_refused():
    g = torch.Generator().manual_seed(4)
    x, W, bb, index = _problem(20, 10, 2, 4, 5, 9, g)
    bad = index.clone()
    bad[3, 2] = 20
    with pytest.raises(RuntimeError, match="index: entry out of range"):
        native.gather_linear(x, W, bb, bad)
    with pytest.raises(RuntimeError, match="index: entry out of range"):
        native.gather_linear(x, W, bb, -index - 1)
    with pytest.raises(RuntimeError, match="weight: expected 36 columns"):
        native.gather_linear(x, W[:, :-1], bb, index)
    with pytest.raises(RuntimeError, match="bias: expected 5 entries"):
        native.gather_linear(x, W, bb[:-1], index)
    with pytest.raises(RuntimeError, match="expected Float"):
        native.gather_linear(x.double(), W, bb, index)


@needs_native
def test_the_flop_counter_counts_the_kernel_as_the_products_of_the_torch_code(torch_threads):
    from torch.utils.flop_counter import FlopCounterMode

    torch.set_num_threads(1)  # the counter sees its own thread only; the torch code deals chunks to workers
    g = torch.Generator().manual_seed(5)
    x, W, bb, index = _problem(30, 30, 4, 6, 7, 9, g)
    with FlopCounterMode(display=False) as fc:
        native.gather_linear(x, W, bb, index)
    with FlopCounterMode(display=False) as ft:
        GatherLinear.apply(x, W, bb, index, GatherLinear.rows_of(index, 4), 1 << 20)
    assert fc.get_total_flops() == ft.get_total_flops() == 2 * 30 * 4 * 7 * 9 * 6


def test_the_conv_takes_the_torch_code_where_the_kernel_does_not_apply(monkeypatch):
    """The conv calls the kernels on float32 CPU tensors, and GatherLinear / PerEntryLinear with
    ``FWK_SPIRALPP_NATIVE=0``, under bf16 autocast and in float64 (``fwk.native.Extension.usable``'s
    own rules: tests/core/test_native.py)."""
    import fwk_spiralpp
    from fwk.graph import torch_sparse
    from fwk.plugins import get_registry
    from fwk.testing.sampler import two_components

    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    U = torch_sparse(h.up[0])
    conv = get_registry().get("conv", "spiral++")(6, 5, h, 0)
    x, xc = torch.randn(2, h.levels[0].n_vertices, 6), torch.randn(2, h.levels[1].n_vertices, 6)
    seen = []
    for name in ("GatherLinear", "PerEntryLinear"):
        cls = getattr(fwk_spiralpp, name)
        monkeypatch.setattr(cls, "apply", (lambda f, n: lambda *a: seen.append(n) or f(*a))(cls.apply, name))

    def torch_code_runs(f=lambda: None):
        seen.clear()
        with torch.no_grad():
            f()
            conv(x), conv.forward_up(xc, U)
        return seen == ["GatherLinear", "PerEntryLinear"]

    assert torch_code_runs() != native.available()
    monkeypatch.setenv("FWK_SPIRALPP_NATIVE", "0")
    assert torch_code_runs()
    monkeypatch.delenv("FWK_SPIRALPP_NATIVE")
    conv.double()
    x, xc = x.double(), xc.double()
    assert torch_code_runs()
    conv.float()
    x, xc = x.float(), xc.float()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch_code_runs()


def _up_problem(n, n_c, b, c, o, L, g):
    """x (n_c, b, c), W (o, L c), bias and S (n, L n_c) with 1-3 random non-zeros a row (a row with none)."""
    rows, cols = [], []
    for i in range(n):
        k = 0 if i == 1 else int(torch.randint(1, 4, (1,), generator=g))
        rows += [i] * k
        cols += torch.randperm(L * n_c, generator=g)[:k].tolist()
    vals = torch.rand(len(rows), generator=g)
    S = torch.sparse_coo_tensor(torch.tensor([rows, cols]), vals, (n, L * n_c)).coalesce()
    St = torch.sparse_coo_tensor(S.indices().flip(0), S.values(), (L * n_c, n)).coalesce()
    return (torch.randn(n_c, b, c, generator=g), torch.randn(o, L * c, generator=g), torch.randn(o, generator=g),
            S.to_sparse_csr(), St.to_sparse_csr())


def _naive_up(x, W, bias, S, L):
    """y[i] = bias + sum over S's non-zeros (i, l n_c + j, u) of u W_l x[j], entry by entry."""
    n_c, b, c = x.shape
    o = W.shape[0]
    y = [bias.expand(b, o) for _ in range(S.shape[0])]
    D = S.to_dense()
    for i, col in D.nonzero().tolist():
        l, j = divmod(col, n_c)
        y[i] = y[i] + D[i, col].to(x.dtype) * (x[j] @ W[:, l * c:(l + 1) * c].T)
    return torch.stack(y)


def _up_call(x, W, bias, S, St, L):
    return native.up_linear(x, native.per_entry(W, L), bias, S.crow_indices(), S.col_indices(), S.values(),
                            St.crow_indices(), St.col_indices(), St.values(), L)


@needs_native
# (60, 200, 16, 3, 8, 3): the products with W_l have n_c b = 3,200 rows, more than one of fwk_native.h's
# tall_mm blocks (2,978 rows at c + o = 11), the last one short; o = 17 and c = 33 take the wide orientation
@pytest.mark.parametrize("shape", [(40, 12, 4, 3, 8, 9), (30, 10, 16, 8, 3, 9), (25, 9, 2, 33, 17, 5),
                                   (60, 200, 16, 3, 8, 3)])
@pytest.mark.parametrize("threads", [1, 2])
def test_up_linear_matches_the_loop_in_float64_in_value_and_gradient(shape, threads, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(sum(shape))
    n, n_c, b, c, o, L = shape
    x, W, bias, S, St = _up_problem(n, n_c, b, c, o, L, g)
    leaves = [t.requires_grad_() for t in (x, W, bias)]
    y = _up_call(x, W, bias, S, St, L)
    gy = torch.randn(y.shape, generator=g)
    got = torch.autograd.grad(y, leaves, gy)
    ref = [t.detach().double().requires_grad_() for t in leaves]
    e = _naive_up(*ref, S, L)
    want = torch.autograd.grad(e, ref, gy.double())
    assert y.shape == (n, b, o) and (y.double() - e).abs().max() <= 1e-5 * (1 + e.abs().max())
    for a, w in zip(got, want):
        assert (a.double() - w).abs().max() <= 1e-5 * (1 + w.abs().max()), (a.double() - w).abs().max()


@needs_native
def test_forward_up_on_the_kernel_equals_the_torch_code_and_repeats_its_bits(monkeypatch):
    """The conv's fused up-sampling on a real hierarchy: the native kernel against PerEntryLinear
    + UpGather, value and gradient."""
    from fwk.graph import torch_sparse
    from fwk.plugins import get_registry
    from fwk.testing.sampler import two_components

    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    U = torch_sparse(h.up[0])
    torch.manual_seed(0)
    conv = get_registry().get("conv", "spiral++")(6, 5, h, 0)
    with torch.no_grad():
        conv.layer.bias.normal_()
    x = torch.randn(3, h.levels[1].n_vertices, 6, requires_grad=True)
    gy = torch.randn(3, h.levels[0].n_vertices, 5)

    def run():
        y = conv.forward_up(x, U)
        return [y.detach()] + [t.clone() for t in torch.autograd.grad(y, (x, *conv.parameters()), gy)]

    nat = run()
    assert all(torch.equal(a, b) for a, b in zip(nat, run())), "same bits on repeat"
    monkeypatch.setenv("FWK_SPIRALPP_NATIVE", "0")
    tor = run()
    for a, t in zip(nat, tor):
        assert (a - t).abs().max() <= 1e-5 * (1 + t.abs().max())


@needs_native
def test_up_linear_refuses_a_malformed_operator():
    g = torch.Generator().manual_seed(6)
    x, W, bias, S, St = _up_problem(20, 8, 2, 4, 3, 9, g)
    with pytest.raises(RuntimeError, match="S: entry out of range"):
        native.up_linear(x, native.per_entry(W, 9), bias, S.crow_indices(), S.col_indices() + 1000, S.values(),
                         St.crow_indices(), St.col_indices(), St.values(), 9)
    with pytest.raises(RuntimeError, match="weight: expected"):  # (L o, c + 1): not x's channels
        native.up_linear(x, torch.randn(27, 5), bias, S.crow_indices(), S.col_indices(), S.values(),
                         St.crow_indices(), St.col_indices(), St.values(), 9)


@needs_native
def test_a_state_loaded_into_one_conv_leaves_the_others_and_is_checked():
    """Every conv on a level gets the level's spirals, which are memoised per topology: each conv keeps a copy of
    its own. A state_dict whose index is out of range, loaded into one conv, changes no other conv's index (nor the
    memo's), and that conv refuses it on its next call instead of reading out of bounds, though the kernel had
    remembered its index as checked (fwk_native.h's PassedChecks: the load writes the buffer in place)."""
    from fwk.plugins import get_registry
    from fwk.testing.sampler import two_components

    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    make = get_registry().get("conv", "spiral++")
    a, b = make(3, 4, h, 0), make(3, 4, h, 0)
    assert a.index.data_ptr() != b.index.data_ptr()
    x = torch.randn(2, h.levels[0].n_vertices, 3)
    with torch.no_grad():
        a(x), b(x)  # both indices checked and remembered
        state = a.state_dict()
        state["index"] = state["index"].clone()
        state["index"][0, 1] = 10 ** 6
        before = b.index.clone()
        a.load_state_dict(state)
        assert torch.equal(b.index, before) and torch.equal(make(3, 4, h, 0).index, before)
        b(x)
        with pytest.raises(RuntimeError, match="out of range"):
            a(x)
