import numpy as np
import pytest
import torch

from fwk.graph import ordered_one_rings, spirals
from fwk.plugins import get_registry
from fwk.testing.conv import ConvContract
from fwk.testing.sampler import two_components


class TestSpiralPPContract(ConvContract):
    component = get_registry().get("conv", "spiral++")
    params = {"length": 9}


def grid(n=5):
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def test_one_rings_are_cyclic_fans():
    F = grid()
    rings = ordered_one_rings(F, 25)
    centre = rings[12]
    assert sorted(centre) == [6, 7, 11, 13, 17, 18]
    # consecutive ring entries share a face with the centre (a walk around the fan)
    faces = {frozenset(map(int, f)) for f in F}
    for a, b in zip(centre, centre[1:] + centre[:1]):
        assert frozenset((12, a, b)) in faces
    corner = rings[0]  # a border vertex: an open fan starting at a border neighbour
    assert corner[0] in (1, 5) and sorted(corner) == [1, 5, 6]


def test_spirals_rings_in_order_and_padding():
    F = grid()
    S = spirals(F, 25, length=9)
    assert S[12, 0] == 12 and set(S[12, 1:7]) == {6, 7, 11, 13, 17, 18}
    assert set(S[12, 7:9]) <= set(range(25)) - {12, 6, 7, 11, 13, 17, 18}
    # a two-triangle component runs out of rings: padded with the centre, never another component
    F2 = np.vstack([F, [[25, 26, 27]]])
    S2 = spirals(F2, 28, length=9)
    assert set(S2[25]) == {25, 26, 27} and list(S2[25][3:]) == [25] * 6
    D = spirals(F, 25, length=4, dilation=2)
    full = spirals(F, 25, length=8)
    assert np.array_equal(D, full[:, ::2])


def naive_spiral(n, v, rings):
    """From the grid's geometry alone: rings by hop distance (dense BFS), each ring sorted by
    angle round v (counter-clockwise), each ring starting at the vertex that continues the
    previous ring: the first vertex strictly counter-clockwise of the previous ring's last one."""
    F = grid(n)
    N = n * n
    A = np.zeros((N, N), bool)
    for f in F:
        for a in range(3):
            A[f[a], f[(a + 1) % 3]] = A[f[(a + 1) % 3], f[a]] = True
    hop = np.full(N, -1)
    hop[v], frontier, k = 0, [v], 0
    while frontier:
        k += 1
        nxt = [u for w in frontier for u in np.flatnonzero(A[w]) if hop[u] < 0]
        for u in nxt:
            hop[u] = k
        frontier = sorted(set(nxt))
    y, x = np.divmod(np.arange(N), n)
    ang = np.arctan2(y - y[v], x - x[v])
    out, prev = [v], None
    for r in range(1, rings + 1):
        ring = sorted(np.flatnonzero(hop == r), key=lambda u: ang[u])
        if prev is None:
            s = min(np.flatnonzero(A[v]))  # the fan of a closed one-ring starts at its smallest neighbour
            start = ring.index(s)
        else:
            turn = [(ang[u] - ang[prev]) % (2 * np.pi) for u in ring]
            start = min((i for i in range(len(ring)) if turn[i] > 1e-9), key=lambda i: turn[i])
        ring = ring[start:] + ring[:start]
        out += ring
        prev = ring[-1]
    return out


def test_spirals_match_a_naive_geometric_construction_on_a_grid():
    n = 9
    F = grid(n)
    for v in (40, 30, 41, 50):  # interior vertices with three complete rings
        S = spirals(F, n * n, length=37)
        assert list(S[v]) == naive_spiral(n, v, 3), v


def _naive_spiralpp(conv, x):
    """x'_i = W [x_{S(i,1)} || ... || x_{S(i,L)}] + b, one vertex at a time."""
    S = conv.index
    return torch.stack([conv.layer(torch.cat([x[:, int(j)] for j in S[i]], -1)) for i in range(S.shape[0])], 1)


def _close(a, e, tol=1e-5):
    return a.shape == e.shape and bool((a - e).abs().max() <= tol * (1 + e.abs().max()))


@pytest.mark.parametrize("c_in,c_out", [(3, 5), (16, 3), (32, 8), (40, 40)])  # both dx paths (c < 32, c >= 32)
@pytest.mark.parametrize("chunk_bytes", [1 << 30, 5000])  # one chunk; many, the last one short
@pytest.mark.parametrize("input_grad", [True, False])
@pytest.mark.parametrize("threads", [1, 3])  # 3: chunks dealt to three workers, their dW and dx summed
@pytest.mark.parametrize("kernel", ["native", "torch"])  # fwk_spiralpp.native, GatherLinear
def test_spiralpp_matches_a_per_vertex_loop_in_value_and_gradient(monkeypatch, c_in, c_out, chunk_bytes, input_grad,
                                                                  threads, kernel):
    import fwk_spiralpp
    from fwk_spiralpp import native

    if kernel == "torch":
        monkeypatch.setenv("FWK_SPIRALPP_NATIVE", "0")
    elif chunk_bytes != 1 << 30:
        pytest.skip("the native kernel has its own blocks (tests/convs/test_spiralpp_native.py)")
    elif not native.available():
        pytest.skip(f"native kernel unavailable: {native.failed()}")
    monkeypatch.setattr(fwk_spiralpp, "CHUNK_BYTES", chunk_bytes)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        _check_against_loop(c_in, c_out, input_grad)
    finally:
        torch.set_num_threads(before)


def _check_against_loop(c_in, c_out, input_grad):
    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    torch.manual_seed(0)
    conv = get_registry().get("conv", "spiral++")(c_in, c_out, h, 1)
    with torch.no_grad():
        conv.layer.bias.normal_()
    n = h.levels[1].n_vertices
    x = torch.randn(3, n, c_in, requires_grad=input_grad)
    g = torch.randn(3, n, c_out)
    y = conv(x)
    (y * g).sum().backward()
    got = ([x.grad.clone()] if input_grad else []) + [p.grad.clone() for p in conv.parameters()]
    if input_grad:
        x.grad = None
    conv.zero_grad()
    expect = _naive_spiralpp(conv, x)
    (expect * g).sum().backward()
    ref = ([x.grad.clone()] if input_grad else []) + [p.grad.clone() for p in conv.parameters()]
    assert _close(y, expect)
    for a, e in zip(got, ref):
        assert _close(a, e), (a - e).abs().max()


def test_spiralpp_takes_a_vertex_major_view_and_runs_under_bf16_autocast():
    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    torch.manual_seed(1)
    conv = get_registry().get("conv", "spiral++")(6, 4, h, 0)
    n = h.levels[0].n_vertices
    xv = torch.randn(n, 2, 6)  # vertex-major storage, as the convs hand their outputs on
    x = xv.transpose(0, 1)
    assert torch.allclose(conv(x), conv(x.contiguous()), atol=1e-6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y16 = conv(x)
    assert y16.dtype == torch.bfloat16
    y = conv(x)
    assert (y16.float() - y).abs().max() <= 0.05 * (1 + y.abs().max())


def test_spiralpp_fused_pooling_under_bf16_autocast():
    """The fused paths under bf16 autocast stay near fp32's plain composition (values and
    gradients in fp32: ConvContract's fused pooling test)."""
    from fwk.graph import sparse_apply, torch_sparse

    h = get_registry().get("sampler", "quadric")(factors=[4, 4]).build(two_components())
    SP = get_registry().get("conv", "spiral++")
    torch.manual_seed(2)
    for level in (0, 1):
        D, U = torch_sparse(h.down[level]).coalesce(), torch_sparse(h.up[level])
        kept = D.indices()[1]
        conv = SP(6, 5, h, level)
        with torch.no_grad():
            conv.layer.bias.normal_()
        pairs = ((lambda v: conv(v, rows=kept), lambda v: sparse_apply(D, conv(v)), h.levels[level].n_vertices),
                 (lambda v: conv.forward_up(v, U), lambda v: conv(sparse_apply(U, v)), h.levels[level + 1].n_vertices))
        for fused, plain, n_in in pairs:
            x = torch.randn(3, n_in, 6)
            e = plain(x)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                y16 = fused(x)
            assert y16.dtype == torch.bfloat16
            assert (y16.float() - e).abs().max() <= 0.05 * (1 + e.abs().max())


def test_spiralpp_up_tables_equal_a_dense_operator_built_by_loops_and_the_product_is_thread_independent():
    """forward_up's sparse operator S against a dense one built entry by entry (S[i, l n_coarse + j] =
    U[s_l(i), j]), its product's gradient by gradcheck (float64), and the product bit for bit
    the same on 1 and 2 threads (each row sums its non-zeros in a fixed order)."""
    from fwk.graph import torch_sparse
    from fwk_spiralpp import UpGather

    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    conv = get_registry().get("conv", "spiral++")(4, 3, h, 0)
    U = torch_sparse(h.up[0]).coalesce()
    S, St = conv._up_tables(U)
    n, n_c = U.shape
    L = conv.length
    parents = {}
    for (r, j), v in zip(U.indices().t().tolist(), U.values().tolist()):
        parents.setdefault(r, []).append((j, v))
    dense = torch.zeros(n, n_c * L)
    for i, spiral in enumerate(conv.index.tolist()):
        for l, s in enumerate(spiral):
            for j, v in parents.get(s, []):
                dense[i, l * n_c + j] += v
    assert torch.allclose(S.to_dense(), dense, atol=0) and torch.allclose(St.to_dense(), dense.t(), atol=0)
    z = torch.randn(n_c * L, 2, dtype=torch.float64, requires_grad=True)
    S64, St64 = S.to(torch.float64), St.to(torch.float64)
    assert torch.autograd.gradcheck(lambda v: UpGather.apply(v, S64, St64), (z,), fast_mode=True)
    threads = torch.get_num_threads()
    big = torch.randn(n_c * L, 4096)
    try:
        torch.set_num_threads(1)
        one = UpGather.apply(big, S, St)
        torch.set_num_threads(2)
        two = UpGather.apply(big, S, St)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)


def test_per_entry_linear_equals_a_loop_and_passes_gradcheck():
    """forward_up's Z_l = x W_l^T (l-major, written into Z's slices) against a loop over entries,
    rows and channels, and its backward by gradcheck (float64), W a strided view as forward_up
    hands it."""
    from fwk_spiralpp import PerEntryLinear

    torch.manual_seed(3)
    m, c, o, L = 7, 3, 4, 5
    x, W = torch.randn(m, c), torch.randn(o, L * c).view(o, L, c)
    Z = PerEntryLinear.apply(x, W)
    ref = torch.zeros(L, m, o)
    for l in range(L):
        for i in range(m):
            for k in range(o):
                ref[l, i, k] = sum(float(x[i, j]) * float(W[k, l, j]) for j in range(c))
    assert Z.shape == (L, m, o) and torch.allclose(Z, ref, atol=1e-5)
    x64 = x.double().requires_grad_()
    W64 = torch.randn(o, L * c, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, w: PerEntryLinear.apply(a, w.view(o, L, c)), (x64, W64))


def test_spiralpp_copies_after_forward_up():
    """A model copied (copy.deepcopy, pickle) after forward_up built its sparse operator copies
    without it (CSR tensors cannot be deep-copied) and rebuilds it: the same output."""
    import copy
    import pickle

    from fwk.graph import torch_sparse

    h = get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())
    conv = get_registry().get("conv", "spiral++")(4, 3, h, 0)
    U = torch_sparse(h.up[0]).coalesce()
    x = torch.randn(2, U.shape[1], 4)
    y = conv.forward_up(x, U)
    assert conv._up is not None
    for other in (copy.deepcopy(conv), pickle.loads(pickle.dumps(conv))):
        assert torch.equal(other.forward_up(x, U), y)
