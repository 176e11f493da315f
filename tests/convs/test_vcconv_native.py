"""vcconv's native kernels (``fwk_vcconv.native``) against per-vertex loops in float64, in value
and gradient; their thread behaviour; their refusals; their multiply-add count. The whole conv on
the native path against the naive sum is ``tests/autoencoders/test_vcconv_naive.py`` (run with
the kernels and without)."""
import os

import pytest
import torch

from fwk_vcconv import native


_NO_BIAS = torch.empty(0)  # the lane kernels' bias argument: none

def test_the_native_kernels_build():
    """CI has a compiler (``.ci/run``): the kernels must build there, not fall back silently."""
    if not native.enabled():
        pytest.skip("FWK_VCCONV_NATIVE=0")
    assert native.available(), native.failed()


pytestmark_native = pytest.mark.skipif(not native.available(), reason=f"native kernels unavailable: {native.failed()}")


def _csr(n_rows, n_target, max_k, g, empty=(1,)):
    """Random supports: row r holds 0..max_k distinct targets (rows in ``empty`` hold none)."""
    offs, idx = [0], []
    for r in range(n_rows):
        k = 0 if r in empty else int(torch.randint(1, max_k + 1, (1,), generator=g))
        idx += torch.randperm(n_target, generator=g)[:k].tolist()
        offs.append(len(idx))
    return torch.tensor(offs), torch.tensor(idx, dtype=torch.long)


def _coefficients(n_slots, M, g, residual, spare=7):
    """coef (R, M) and w (R) with R = slots + spare rows no slot reads, and pos: each slot's row."""
    R = n_slots + spare
    coef = torch.randn(R, M, generator=g, requires_grad=True)
    w = torch.randn(R, generator=g, requires_grad=True) if residual else torch.empty(0)
    return coef, w, torch.randperm(R, generator=g)[:n_slots]


def _naive_sum(x, coef, w, offs, src, pos):
    T, r = [], []
    for i in range(len(offs) - 1):
        sl = slice(int(offs[i]), int(offs[i + 1]))
        X = x[src[sl]]  # (K, B)
        T.append(X.T @ coef[pos[sl]])
        if w.numel():
            r.append(X.T @ w[pos[sl]])
    return torch.stack(T), (torch.stack(r) if r else None)


def _naive_basis(Z, coef, offs, dst, pos, n_out):
    y = Z.new_zeros(n_out, Z.shape[1])
    for j in range(len(offs) - 1):
        for s in range(int(offs[j]), int(offs[j + 1])):
            y[dst[s]] = y[dst[s]] + Z[j] @ coef[pos[s]]
    return y


def _grads(out, inputs, upstream):
    return torch.autograd.grad(out, inputs, upstream, allow_unused=True)


def _double(*ts):
    return [t.detach().double().requires_grad_(t.requires_grad) for t in ts]


def _offer_nan(*ts):
    """Freed memory of each tensor's shape, full of NaN, for the backward to be given: with every
    coefficient row named by a slot (``spare`` 0) the kernels write each row's gradient into an
    unfilled buffer, and a row left unwritten would show."""
    for t in ts:
        for _ in range(3):
            torch.full(t.shape, float("nan"))


@pytestmark_native
@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("B,M,lanes", [(12, 5, True), (12, 5, False), (37, 16, True), (128, 35, True), (150, 35, True),
                                        (20, 63, True),
                                        (20, 64, False), (20, 28, True), (20, 40, True), (20, 52, True)])
@pytest.mark.parametrize("spare", [7, 0])
def test_sum_product_matches_the_loops_in_value_and_gradient(residual, threads, B, M, lanes, spare, torch_threads,
                                                             monkeypatch):
    """T and r against the per-vertex loops in float64, on the per-vertex BLAS call and (``lanes``,
    where the CPU runs them) its lane path (``sum_vertex_lanes``, and ``sum_vertex_lanes_backward`` for the
    coefficients' gradient): rows in blocks of 8 and the rest, slots in blocks of 4 and the rest, kernels (and the
    residual's column) in every layout of ``KernelChunks`` (1-4 vectors of 16, with and without a half vector for
    the last 1-8); coefficient rows no slot reads (``spare``) or none."""
    if not lanes:
        monkeypatch.setattr(native, "lanes", lambda M=1: False)
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    n_in, n_out = 23, 9
    offs, src = _csr(n_out, n_in, 6, g)
    x = torch.randn(n_in, B, generator=g, requires_grad=True)
    coef, w, pos = _coefficients(len(src), M, g, residual, spare=spare)
    T, r = native.sum_product(x, coef, w, offs, src, pos)
    _offer_nan(coef, w)
    xd, cd, wd = _double(x, coef, w)
    Te, re = _naive_sum(xd, cd, wd, offs, src, pos)
    assert torch.allclose(T.double(), Te, atol=1e-5)
    assert (T[1] == 0).all(), "an empty support gives zeros"
    gT = torch.randn(T.shape, generator=g)
    if residual:
        assert torch.allclose(r.double(), re, atol=1e-5)
        gr = torch.randn(r.shape, generator=g)
        got, exp = _grads((T, r), (x, coef, w), (gT, gr)), _grads((Te, re), (xd, cd, wd), (gT.double(), gr.double()))
    else:
        assert r.numel() == 0
        got, exp = _grads(T, (x, coef), gT), _grads(Te, (xd, cd), gT.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, atol=1e-4)
    unread = torch.ones(len(coef), dtype=torch.bool)
    unread[pos] = False
    assert (got[1][unread] == 0).all(), "a coefficient row no slot reads gets no gradient"


@pytestmark_native
@pytest.mark.parametrize("lanes", [True, False])
def test_a_range_shorter_than_the_threads_leaves_no_accumulator_unzeroed(lanes, torch_threads, monkeypatch):
    """One output vertex on 2 threads: at::parallel_for runs the range in one thread, so one of the per-thread
    accumulators (fwk_native's ``ThreadAccumulators``, zeroed by their own threads) is never handed a part; it is
    zeroed before the sum (``done``), and the gradient is the loops' (memory full of NaN offered first, as a buffer
    left unzeroed would show)."""
    if not lanes:
        monkeypatch.setattr(native, "lanes", lambda M=1: False)
    elif not native.lanes(35):
        pytest.skip("the lane kernels do not run on this CPU")
    torch.set_num_threads(2)
    g = torch.Generator().manual_seed(3)
    offs, src = _csr(1, 5, 4, g, empty=())
    x = torch.randn(5, 32, generator=g, requires_grad=True)
    coef, w, pos = _coefficients(len(src), 35, g, True)
    T, r = native.sum_product(x, coef, w, offs, src, pos)
    gT, gr = torch.randn(T.shape, generator=g), torch.randn(r.shape, generator=g)
    for _ in range(3):
        torch.full((2, 5, 32), float("nan"))
    got = _grads((T, r), (x,), (gT, gr))[0]
    xd, cd, wd = _double(x, coef, w)
    Te, re = _naive_sum(xd, cd, wd, offs, src, pos)
    exp = _grads((Te, re), (xd,), (gT.double(), gr.double()))[0]
    assert torch.allclose(got.double(), exp, atol=1e-4)


def _naive_kernel(x, Wk, w, offs, src, pos, b, c, o):
    """y_i = sum_k x[src_k] (b x c) @ Wk[pos_k] (c x o), r_i = sum_k w[pos_k] x[src_k], slot by slot."""
    y, r = [], []
    for i in range(len(offs) - 1):
        yi, ri = x.new_zeros(b, o), x.new_zeros(b * c)
        for s in range(int(offs[i]), int(offs[i + 1])):
            yi = yi + x[src[s]].reshape(b, c) @ Wk[pos[s]].reshape(c, o)
            if w.numel():
                ri = ri + w[pos[s]] * x[src[s]]
        y.append(yi)
        r.append(ri)
    return torch.stack(y), (torch.stack(r) if w.numel() else None)


@pytestmark_native
@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("b,c,o", [(4, 3, 8), (3, 5, 17), (2, 16, 3)])  # narrow and wide results
@pytest.mark.parametrize("spare", [7, 0])
def test_kernel_product_matches_the_loops_in_value_and_gradient(residual, threads, b, c, o, spare, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(b + c + o)
    n_in, n_out = 23, 9
    offs, src = _csr(n_out, n_in, 6, g)
    x = torch.randn(n_in, b * c, generator=g, requires_grad=True)
    Wk, w, pos = _coefficients(len(src), c * o, g, residual, spare=spare)
    y, r = native.kernel_product(x, Wk, w, offs, src, pos, b, c, o)
    _offer_nan(Wk, w)
    xd, Wd, wd = _double(x, Wk, w)
    ye, re = _naive_kernel(xd, Wd, wd, offs, src, pos, b, c, o)
    assert y.shape == (n_out, b, o) and torch.allclose(y.double(), ye, atol=1e-5)
    assert (y[1] == 0).all(), "an empty support gives zeros"
    gy = torch.randn(y.shape, generator=g)
    if residual:
        assert torch.allclose(r.double(), re, atol=1e-5)
        gr = torch.randn(r.shape, generator=g)
        got, exp = _grads((y, r), (x, Wk, w), (gy, gr)), _grads((ye, re), (xd, Wd, wd), (gy.double(), gr.double()))
    else:
        assert r.numel() == 0
        got, exp = _grads(y, (x, Wk), gy), _grads(ye, (xd, Wd), gy.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, atol=1e-4)
    unread = torch.ones(len(Wk), dtype=torch.bool)
    unread[pos] = False
    assert (got[1][unread] == 0).all(), "a kernel row no slot reads gets no gradient"


@pytestmark_native
def test_kernel_product_refuses_malformed_arguments_and_is_counted():
    from torch.utils.flop_counter import FlopCounterMode

    x, Wk, w = torch.randn(4, 6), torch.randn(3, 6), torch.randn(3)
    pos, offs, src = torch.tensor([0, 1, 2]), torch.tensor([0, 2, 3]), torch.tensor([0, 1, 1])
    with pytest.raises(RuntimeError, match="out of range"):
        native.kernel_product(x, Wk, w, offs, torch.tensor([0, 4, 1]), pos, 2, 3, 2)
    with pytest.raises(RuntimeError, match="named twice"):
        native.kernel_product(x, Wk, w, offs, src, torch.tensor([0, 1, 1]), 2, 3, 2)
    with pytest.raises(RuntimeError, match="b c"):
        native.kernel_product(x, Wk, w, offs, src, pos, 3, 3, 2)
    with pytest.raises(RuntimeError, match="c o"):
        native.kernel_product(x, Wk, w, offs, src, pos, 2, 3, 3)
    with FlopCounterMode(display=False) as fc:
        native.kernel_product(x, Wk, w, offs, src, pos, 2, 3, 2)
    assert fc.get_total_flops() == 2 * 3 * 2 * 3 * (2 + 1)  # slots x b x c x (o + the residual's weight)


@pytestmark_native
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("spare", [7, 0])
def test_basis_product_matches_the_loops_in_value_and_gradient(threads, spare, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(1)
    n_in, n_out, B, M = 11, 30, 10, 4
    offs, dst = _csr(n_in, n_out, 7, g, empty=(2, 5))
    Z = torch.randn(n_in, B, M, generator=g, requires_grad=True)
    coef, _, pos = _coefficients(len(dst), M, g, False, spare=spare)
    y = native.basis_product(Z, coef, offs, dst, pos, n_out)
    _offer_nan(coef)
    Zd, cd = _double(Z, coef)
    ye = _naive_basis(Zd, cd, offs, dst, pos, n_out)
    assert torch.allclose(y.double(), ye, atol=1e-5)
    gy = torch.randn(y.shape, generator=g)
    got, exp = _grads(y, (Z, coef), gy), _grads(ye, (Zd, cd), gy.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, atol=1e-4)
    assert (got[0][2] == 0).all(), "an input vertex no output holds gets no gradient"


@pytestmark_native
def test_the_same_thread_count_gives_the_same_bits(torch_threads):
    """Scatters go to per-thread accumulators split statically and summed in thread order."""
    torch.set_num_threads(2)
    g = torch.Generator().manual_seed(2)
    offs, dst = _csr(200, 150, 9, g)
    Z = torch.randn(200, 64, 7, generator=g, requires_grad=True)
    coef, _, pos = _coefficients(len(dst), 7, g, False)
    runs = []
    for _ in range(3):
        y = native.basis_product(Z, coef.detach(), offs, dst, pos, 150)
        (dZ,) = torch.autograd.grad(y, Z, torch.ones_like(y))
        runs.append((y, dZ))
    for y, dZ in runs[1:]:
        assert torch.equal(y, runs[0][0]) and torch.equal(dZ, runs[0][1])


@pytestmark_native
def test_malformed_supports_are_refused_not_read_out_of_bounds():
    x, coef, w, none = torch.randn(4, 3), torch.randn(3, 2), torch.randn(3), torch.empty(0)
    pos, offs, src = torch.tensor([0, 1, 2]), torch.tensor([0, 2, 3]), torch.tensor([0, 1, 1])
    with pytest.raises(RuntimeError, match="out of range"):
        native.sum_product(x, coef, w, offs, torch.tensor([0, 4, 1]), pos)
    with pytest.raises(RuntimeError, match="out of range"):
        native.sum_product(x, coef, w, offs, src, torch.tensor([0, 1, 3]))
    with pytest.raises(RuntimeError, match="named twice"):
        native.sum_product(x, coef, w, offs, src, torch.tensor([0, 1, 1]))
    with pytest.raises(RuntimeError, match="slot count"):
        native.sum_product(x, coef, none, torch.tensor([0, 2, 2]), src, pos)
    with pytest.raises(RuntimeError, match="decrease"):
        native.basis_product(torch.randn(3, 3, 2), coef, torch.tensor([0, 3, 2, 3]), src, pos, 3)
    with pytest.raises(RuntimeError, match="one weight per"):
        native.sum_product(x, coef, torch.randn(2), offs, src, pos)
    with pytest.raises(RuntimeError, match="Float"):
        native.sum_product(x.double(), coef.double(), none, offs, src, pos)
    empty = torch.empty(0, dtype=torch.long)  # no offsets at all: refused before any is read
    with pytest.raises(RuntimeError, match="at least 1"):
        native.weighted_rows(x, w, empty, src, pos, empty, src, pos)
    with pytest.raises(RuntimeError, match="at least 1"):
        native.residual_weights(w, empty, pos, 1.0)


@pytestmark_native
def test_the_flop_counter_counts_the_kernels_multiply_adds():
    from torch.utils.flop_counter import FlopCounterMode

    g = torch.Generator().manual_seed(3)
    offs, idx = _csr(8, 20, 5, g)
    x = torch.randn(20, 6, generator=g)
    coef, w, pos = _coefficients(len(idx), 3, g, True)
    with FlopCounterMode(display=False) as fc:
        native.sum_product(x, coef.detach(), w.detach(), offs, idx, pos)  # M + 1 = 4 columns with the weights
        native.basis_product(torch.randn(8, 6, 4, generator=g), torch.randn(len(idx), 4, generator=g), offs, idx,
                             torch.arange(len(idx)), 20)
    assert fc.get_total_flops() == 2 * len(idx) * 6 * 4 * 2


def _in_side(offs, src, n_in):
    """The same slots listed by input vertex: (in_offs, in_dst, slot index per entry)."""
    n_out = len(offs) - 1
    rows = torch.repeat_interleave(torch.arange(n_out), offs[1:] - offs[:-1])
    order = torch.sort(src, stable=True).indices
    in_offs = torch.cat([torch.zeros(1, dtype=torch.long), torch.bincount(src, minlength=n_in).cumsum(0)])
    return in_offs, rows[order], order


@pytestmark_native
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("spare", [7, 0])
@pytest.mark.parametrize("B", [1, 48, 37])
def test_weighted_rows_matches_the_loops_in_value_and_gradient(threads, spare, B, torch_threads):
    """r_i = sum_s w[pos[s]] x[src[s]] against the loop in float64, value and gradients, with an output of no
    slots (a zero row), an input no slot reads (no gradient) and weight rows no slot names (zero gradient)."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(21)
    n_in, n_out = 17, 30
    offs, src = _csr(n_out, n_in, 6, g, empty=(1, 4))
    src[src == 3] = 5  # input 3 in no support (duplicates within a support are allowed: slots, not neighbours)
    x = torch.randn(n_in, B, generator=g, requires_grad=True)
    _, w, pos = _coefficients(len(src), 1, g, True, spare=spare)
    in_offs, in_dst, order = _in_side(offs, src, n_in)
    r = native.weighted_rows(x, w, offs, src, pos, in_offs, in_dst, pos[order])
    xd, wd = _double(x, w)
    re = torch.stack([sum((wd[pos[s]] * xd[src[s]] for s in range(int(offs[i]), int(offs[i + 1]))),
                          xd.new_zeros(B)) for i in range(n_out)])
    assert torch.allclose(r.double(), re, atol=1e-5)
    assert (r[1] == 0).all() and (r[4] == 0).all()
    gr = torch.randn(r.shape, generator=g)
    _offer_nan(w)
    got, exp = _grads(r, (x, w), gr), _grads(re, (xd, wd), gr.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, atol=1e-4)
    assert (got[0][3] == 0).all(), "an input no slot reads gets no gradient"
    read = torch.zeros(w.shape[0], dtype=torch.bool)
    read[pos] = True
    assert (got[1][~read] == 0).all()


@pytestmark_native
@pytest.mark.parametrize("threads", [1, 2])
def test_residual_weights_match_torchs_normalisation_in_value_and_gradient(threads, torch_threads):
    """wn = scale |w| / max(sum |w| over the output's slots, 1e-12) as vcconv's torch code computes it, value and
    gradient, with a zero weight (abs' gradient 0 there), an output whose weights are all zero (clamped: no
    gradient through the sum) and rows no slot names."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(22)
    n_out, R = 40, 200
    offs, _ = _csr(n_out, 1000, 8, g, empty=(3,))
    slots = int(offs[-1])
    pos = torch.randperm(R, generator=g)[:slots]
    w = torch.randn(R, generator=g)
    w[pos[int(offs[5])]] = 0.0
    w[pos[int(offs[7]):int(offs[8])]] = 0.0
    w.requires_grad_()
    scale = 0.5 ** 0.5
    wn = native.residual_weights(w, offs, pos, scale)
    wd = w.detach().double().requires_grad_()
    rows = torch.repeat_interleave(torch.arange(n_out), offs[1:] - offs[:-1])
    a = wd.abs()[pos]
    total = a.new_zeros(n_out).index_add_(0, rows, a)
    we = wd.new_zeros(R).index_put((pos,), a * (scale / total.clamp_min(1e-12))[rows])
    assert torch.allclose(wn.double(), we, atol=1e-6)
    gw = torch.randn(R, generator=g)
    (got,), (exp,) = _grads(wn, (w,), gw), _grads(we, (wd,), gw.double())
    assert torch.allclose(got.double(), exp, atol=1e-5)
    named = torch.zeros(R, dtype=torch.bool)
    named[pos] = True
    assert (wn[~named] == 0).all() and (got[~named] == 0).all()


@pytestmark_native
def test_a_passed_check_is_done_again_after_the_index_changes():
    """The kernels remember which index tensors passed their checks (fwk_native.h's PassedChecks); an in-place
    write to one, or another tensor in its place, is checked again: an out-of-range entry is refused, not read."""
    x, w = torch.randn(5, 4), torch.rand(3)
    offs, src, pos = torch.tensor([0, 2, 3]), torch.tensor([0, 4, 2]), torch.tensor([2, 0, 1])
    in_offs, in_dst, order = _in_side(offs, src, 5)
    args = (offs, src, pos, in_offs, in_dst, pos[order])
    native.weighted_rows(x, w, *args)  # passes, remembered
    native.weighted_rows(x, w, *args)
    src[1] = 9  # in place: its version counter moves
    with pytest.raises(RuntimeError, match="out of range"):
        native.weighted_rows(x, w, *args)
    src[1] = 4
    native.weighted_rows(x, w, *args)
    pos[0] = 0  # now named twice
    with pytest.raises(RuntimeError, match="named twice"):
        native.weighted_rows(x, w, *args)
    pos[0] = 2
    native.weighted_rows(x, w, *args)
    del src  # a fresh tensor, maybe at the freed one's address, with a bad entry
    bad = torch.tensor([0, 4, 7])
    with pytest.raises(RuntimeError, match="out of range"):
        native.weighted_rows(x, w, offs, bad, pos, in_offs, in_dst, pos[order])
    with pytest.raises(RuntimeError, match="out of range"):
        native.sum_product(x, torch.randn(3, 2), w, offs, bad, pos)


def test_the_torch_code_runs_when_the_kernels_are_off_or_do_not_apply(monkeypatch):
    """``FWK_VCCONV_NATIVE=0``, bf16 autocast and float64 take VCConv's torch evaluation."""
    x = torch.randn(3, 4)
    monkeypatch.setenv("FWK_VCCONV_NATIVE", "0")
    assert not native.usable(x)
    monkeypatch.delenv("FWK_VCCONV_NATIVE")
    assert not native.usable(x.double())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not native.usable(x)
    assert native.usable(x) == native.available()


def test_without_a_compiler_vcconv_says_so_once_and_runs_its_torch_code(tmp_path):
    import subprocess
    import sys

    code = ("import torch\n"
            "from fwk.plugins import get_registry\n"
            "from fwk.testing.sampler import two_components\n"
            "from fwk_vcconv import native\n"
            "h = get_registry().get('sampler', 'simple')(levels=2).build(two_components())\n"
            "conv = get_registry().get('conv', 'vcconv')(3, 4, h, 0, weight_num=5, mode='down', residual_rate=0.5)\n"
            "y = conv(torch.randn(2, conv.n_in, 3)); y.sum().backward(); conv(torch.randn(2, conv.n_in, 3))\n"
            "print('available', native.available(), tuple(y.shape))\n")
    env = {**os.environ, "CXX": str(tmp_path / "no-such-compiler"), "TORCH_EXTENSIONS_DIR": str(tmp_path / "ext")}
    env.pop("FWK_VCCONV_NATIVE", None)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "available False" in out.stdout
    assert out.stderr.count("native kernels unavailable") == 1, out.stderr[-2000:]


# ---- the products with the basis (``tall_product``)
TALL_SHAPES = [(700, 8, 105), (700, 105, 8), (513, 3, 8), (300, 40, 16), (9, 5, 3), (1, 4, 20), (37, 7, 64),
               (101, 64, 33), (33, 9, 128)]  # N >= 16 and N < 16, N >= K and N < K (the two orientations of each product), a partial
# last block, fewer rows than a block; in lanes (results of at most 128 columns: the forward's N, dA's K): 1-8 vectors
# a row (4 at a time), the last one partial or whole, rows in blocks of 8 or 4 and the rest


@pytestmark_native
@pytest.mark.parametrize("R,K,N", TALL_SHAPES)
@pytest.mark.parametrize("bias", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("lanes", [True, False])
def test_tall_product_matches_the_dense_product_in_value_and_gradient(R, K, N, bias, threads, lanes, torch_threads,
                                                                     monkeypatch):
    """C, dA and dB against float64 products, by the lane kernel (``tall_lanes``, where the CPU runs it) and by
    the BLAS calls on row blocks (``tall_mm``)."""
    if not lanes:
        monkeypatch.setattr(native, "lanes", lambda M=1: False)
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(R + K + N)
    A, B, b, up = (torch.randn(*s, generator=g, dtype=torch.float64) for s in ((R, K), (K, N), (N,), (R, N)))
    Af, Bf, bf = (t.float().requires_grad_() for t in (A, B, b))
    C = native.tall_product(Af, Bf, bf if bias else Af.new_empty(0))
    ref = A @ B + (b if bias else 0)
    got = torch.autograd.grad(C, (Af, Bf, bf) if bias else (Af, Bf), up.float())
    want = (up @ B.t(), A.t() @ up, up.sum(0))
    for x, y in zip((C, *got), (ref, *want)):
        assert x.shape == y.shape
        assert torch.allclose(x.double(), y, rtol=1e-5, atol=1e-5 * y.abs().max().item()), (x.double() - y).abs().max()


@pytestmark_native
def test_tall_product_is_the_same_bits_on_repeat_and_its_forward_on_any_thread_count(torch_threads):
    """The forward's row blocks do not depend on the thread count; the gradient of B sums per
    thread in thread order (the same bits with the same count)."""
    g = torch.Generator().manual_seed(7)
    A, B, b = torch.randn(5000, 105, generator=g), torch.randn(105, 8, generator=g), torch.randn(8, generator=g)
    runs = {}
    for threads in (1, 2, 2):
        torch.set_num_threads(threads)
        Bg = B.clone().requires_grad_()
        C = native.tall_product(A, Bg, b)
        (dB,) = torch.autograd.grad(C, Bg, torch.ones_like(C))
        if threads in runs:
            assert torch.equal(C, runs[threads][0]) and torch.equal(dB, runs[threads][1])
        runs[threads] = (C, dB)
    assert torch.equal(runs[1][0], runs[2][0])


@pytestmark_native
def test_tall_product_refuses_mismatched_shapes():
    A, B = torch.randn(10, 4), torch.randn(4, 3)
    with pytest.raises(RuntimeError, match="expected 4 rows"):
        native.tall_product(A, torch.randn(5, 3), A.new_empty(0))
    with pytest.raises(RuntimeError, match="bias"):
        native.tall_product(A, B, torch.randn(4))
    with pytest.raises(RuntimeError, match="Float"):
        native.tall_product(A.double(), B.double(), A.new_empty(0).double())


@pytestmark_native
def test_the_flop_counter_counts_tall_products():
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc:
        native.tall_product(torch.randn(50, 7), torch.randn(7, 3), torch.empty(0))
    assert fc.get_total_flops() == 2 * 50 * 7 * 3


def test_vcconv_takes_tall_product_for_tall_narrow_products_only():
    """``tall``: the shapes MKL runs slowly (many rows, a small B); the thesis width's 64 x 1120
    basis stays with torch's product."""
    assert native.tall(torch.empty(49424, 105), torch.empty(105, 8))
    assert native.tall(torch.empty(49424, 8), torch.empty(8, 105))
    assert not native.tall(torch.empty(10096, 64), torch.empty(64, 1120))
    assert not native.tall(torch.empty(100, 8), torch.empty(8, 105))


# ---- the basis order in lanes (native.basis_lanes)
pytestmark_lanes = pytest.mark.skipif(not (native.available() and native.lanes(35)),
                                      reason="the lane kernels need the native kernels and an AVX-512 CPU")


def _naive_basis_lanes(x, basis, coef, offs, dst, pos, n_out):
    """The basis order by its definition, slot by slot: y[dst[s]] += x_j (sum_m A_sm B_m) for input vertex j."""
    b, o = x.shape[1], basis.shape[2]
    y = x.new_zeros(n_out, b, o)
    for j in range(len(offs) - 1):
        for s in range(int(offs[j]), int(offs[j + 1])):
            W = torch.einsum("m,mpq->pq", coef[pos[s]], basis)  # the slot's c x o kernel
            y[dst[s]] = y[dst[s]] + x[j] @ W
    return y


@pytestmark_lanes
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("b,c,o,M", [(16, 8, 3, 35), (5, 3, 8, 7), (20, 4, 5, 16), (33, 2, 1, 64), (1, 6, 7, 17),
                                     (16, 16, 8, 35), (7, 11, 2, 33), (20, 5, 4, 24), (9, 2, 3, 28), (16, 3, 3, 45),
                                     (4, 4, 2, 52), (20, 32, 16, 35)])
@pytest.mark.parametrize("spare", [7, 0])
@pytest.mark.parametrize("fwd", [0, 1, 2])
def test_basis_lanes_matches_the_slot_loop_in_value_and_gradient(threads, b, c, o, M, spare, fwd, torch_threads,
                                                                  monkeypatch):
    """Batches of 16 and not (the lanes past b are zero; past 16, the first group writes a coefficient
    row's gradient and the others add to it), kernel counts in every layout of the dA and Zm paths (``KernelChunks``:
    1-4 vectors of 16, with and without a half vector for the last 1-8; 24 and 40 fill it),
    supports of 0 to 9 slots, the forward by either route (``LANES_FORWARD``: the cheaper, through Z_j, through each
    slot's kernel where c o <= 64, slots in blocks of 4 and the rest): value and gradients of x, the basis and the
    coefficients against the slot loop in float64; coefficient rows no slot reads get zero (``spare``), or there
    are none (``_offer_nan``)."""
    if fwd == 2 and c * o > 64:
        pytest.skip("route 2 of the forward takes c o <= 64")
    monkeypatch.setattr(native, "LANES_FORWARD", fwd)
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(11)
    n_in, n_out = 13, 40
    offs, dst = _csr(n_in, n_out, 9, g, empty=(2, 7))
    x = torch.randn(n_in, b, c, generator=g, requires_grad=True)
    basis = torch.randn(M, c, o, generator=g, requires_grad=True)
    coef, _, pos = _coefficients(len(dst), M, g, False, spare=spare)
    y = native.basis_lanes(x, basis, coef, offs, dst, pos, n_out, _NO_BIAS)
    xd, bd, cd = _double(x, basis, coef)
    ye = _naive_basis_lanes(xd, bd, cd, offs, dst, pos, n_out)
    assert y.shape == (n_out, b, o)
    assert torch.allclose(y.double(), ye, rtol=1e-5, atol=1e-4)
    gy = torch.randn(y.shape, generator=g)
    _offer_nan(coef)
    got, exp = _grads(y, (x, basis, coef), gy), _grads(ye, (xd, bd, cd), gy.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, rtol=1e-5, atol=1e-3), (a.double() - e).abs().max()
    assert (got[0][2] == 0).all() and (got[0][7] == 0).all(), "an input vertex with no slots gets no gradient"
    read = torch.zeros(coef.shape[0], dtype=torch.bool)
    read[pos] = True
    assert (got[2][~read] == 0).all(), "coefficient rows no slot reads get no gradient"


@pytestmark_lanes
def test_basis_lanes_is_the_same_bits_on_repeat_and_asks_only_what_is_needed(torch_threads):
    torch.set_num_threads(2)
    g = torch.Generator().manual_seed(12)
    offs, dst = _csr(300, 700, 12, g)
    x = torch.randn(300, 16, 8, generator=g)
    basis = torch.randn(35, 8, 3, generator=g)
    coef, _, pos = _coefficients(len(dst), 35, g, False)
    coef = coef.detach()
    runs = [native.basis_lanes(x, basis, coef, offs, dst, pos, 700, _NO_BIAS) for _ in range(3)]
    assert all(torch.equal(r, runs[0]) for r in runs[1:])
    xr = x.clone().requires_grad_()
    (dx,) = torch.autograd.grad(native.basis_lanes(xr, basis, coef, offs, dst, pos, 700, _NO_BIAS).sum(), xr)
    (dx2,) = torch.autograd.grad(native.basis_lanes(xr, basis, coef, offs, dst, pos, 700, _NO_BIAS).sum(), xr)
    assert torch.equal(dx, dx2)


@pytestmark_lanes
def test_basis_lanes_refuses_malformed_arguments_and_is_counted():
    from torch.utils.flop_counter import FlopCounterMode

    x, basis, coef = torch.randn(3, 4, 2), torch.randn(5, 2, 3), torch.randn(4, 5)
    offs, dst, pos = torch.tensor([0, 2, 2, 4]), torch.tensor([0, 1, 1, 2]), torch.tensor([3, 0, 1, 2])
    with pytest.raises(RuntimeError, match="out of range"):
        native.basis_lanes(x, basis, coef, offs, torch.tensor([0, 1, 1, 3]), pos, 3, _NO_BIAS)
    with pytest.raises(RuntimeError, match="named twice"):
        native.basis_lanes(x, basis, coef, offs, dst, torch.tensor([0, 0, 1, 2]), 3, _NO_BIAS)
    with pytest.raises(RuntimeError, match="input channels"):
        native.basis_lanes(x, torch.randn(5, 3, 3), coef, offs, dst, pos, 3, _NO_BIAS)
    with pytest.raises(RuntimeError, match="1 to 64 kernels"):
        native.basis_lanes(x, torch.randn(65, 2, 3), torch.randn(4, 65), offs, dst, pos, 3, _NO_BIAS)
    with pytest.raises(RuntimeError, match="Float"):
        native.basis_lanes(x.double(), basis.double(), coef.double(), offs, dst, pos, 3, _NO_BIAS)
    assert not native.lanes(65) and native.lanes(64)
    with FlopCounterMode(display=False) as fc:
        native.basis_lanes(x, basis, coef, offs, dst, pos, 3, _NO_BIAS)
    assert fc.get_total_flops() == 2 * 3 * 4 * 2 * 5 * 3 + 2 * 4 * 5 * 4 * 3  # as the tall product and basis_product


def _lanes_against_off(monkeypatch, op, limit, c_in, c_out, mode, order, record):
    """A small vcconv layer (levels 1 <-> 2 of the two-component mesh) in ``order``, run with the lane
    limit ``limit`` of ``fwk_vcconv`` as it is and at 0: the calls of ``native.<op>`` the first run
    made (``record`` of its arguments), after asserting that both runs agree in value and in the
    gradients of the input and every parameter (the same sums in another order: equal to float32
    rounding of the largest entry)."""
    import fwk_vcconv
    from fwk.plugins import get_registry
    from fwk.testing.sampler import two_components

    h = get_registry().get("sampler", "simple")(levels=3).build(two_components())
    torch.manual_seed(0)
    conv = get_registry().get("conv", "vcconv")(c_in, c_out, h, 1, weight_num=5, mode=mode, residual_rate=0.5,
                                                order=order)
    calls = []
    real = getattr(native, op)
    monkeypatch.setattr(native, op, lambda *a: calls.append(record(*a)) or real(*a))
    x = torch.randn(3, conv.n_in, c_in, requires_grad=True)
    runs = []
    for value in (getattr(fwk_vcconv, limit), 0):
        monkeypatch.setattr(fwk_vcconv, limit, value)
        y = conv(x)
        runs.append((y, *torch.autograd.grad(y.square().sum(), [x, *conv.parameters()])))
    for a, e in zip(*runs):
        assert (a - e).abs().max() <= 1e-5 * (1 + e.abs().max())
    return calls


@pytestmark_lanes
@pytest.mark.parametrize("c_in,c_out,lanes", [(6, 3, True), (6, 8, True), (6, 16, True), (6, 17, False), (32, 4, True),
                                              (33, 4, False)])
def test_vcconv_runs_narrow_basis_layers_in_lanes(c_in, c_out, lanes, monkeypatch):
    """The ``basis`` order of a layer with at most ``LANES_MAX_IN`` input and ``LANES_MAX_OUT`` output channels
    takes ``basis_lanes``, a wider one the tall product and ``basis_product``; with lanes off
    (``LANES_MAX_OUT = 0``) the same layer agrees in value and gradient."""
    calls = _lanes_against_off(monkeypatch, "basis_lanes", "LANES_MAX_OUT", c_in, c_out, "up", "basis",
                               lambda x, basis, *rest: basis.shape)
    assert calls == ([(5, c_in, c_out)] if lanes else [])


def _naive_kernel_lanes(x, Wk, w, offs, src, pos, o):
    """y_i = sum_s x_src[s] W_pos[s] and r_i = sum_s w_pos[s] x_src[s], slot by slot."""
    n_out, (b, c) = len(offs) - 1, x.shape[1:]
    y, r = x.new_zeros(n_out, b, o), x.new_zeros(n_out, b, c)
    for i in range(n_out):
        for s in range(int(offs[i]), int(offs[i + 1])):
            y[i] = y[i] + x[src[s]] @ Wk[pos[s]].reshape(c, o)
            if w.numel():
                r[i] = r[i] + w[pos[s]] * x[src[s]]
    return y, r


@pytestmark_lanes
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("b,c,o,residual", [(16, 3, 8, True), (5, 8, 16, False), (20, 4, 5, True), (33, 2, 11, True),
                                            (16, 9, 8, True), (17, 64, 32, True), (3, 40, 27, False)])
def test_kernel_lanes_matches_the_slot_loop_in_value_and_gradient(threads, b, c, o, residual, torch_threads):
    """``kernel_lanes`` (the kernel order, 16 batch entries a register; the kernels' gradient from the
    batch-major rows, two slots at a time) against the slot loop in float64: y, the residual's average, and the
    gradients of x, the kernels and the residual's weights, and of the kernels and weights alone (an input that
    needs no gradient: the first layer's); batches of 16 and not, supports of 0-9 slots, odd and even."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(13)
    offs, src = _csr(11, 30, 9, g, empty=(2,))
    x = torch.randn(30, b, c, generator=g, requires_grad=True)
    Wk, w, pos = _coefficients(len(src), c * o, g, residual)
    y, r = native.kernel_lanes(x, Wk, w, offs, src, pos, o, _NO_BIAS)
    xd, Wd, wd = _double(x, Wk, w)
    ye, re = _naive_kernel_lanes(xd, Wd, wd, offs, src, pos, o)
    assert torch.allclose(y.double(), ye, atol=1e-4)
    gy, gr = torch.randn(y.shape, generator=g), torch.randn(re.shape, generator=g)
    out, oute = (y * gy).sum(), (ye * gy.double()).sum()
    if residual:
        assert torch.allclose(r.double(), re, atol=1e-5)
        out, oute = out + (r * gr).sum(), oute + (re * gr.double()).sum()
    else:
        assert r.numel() == 0
    ins, insd = ((x, Wk, w), (xd, Wd, wd)) if residual else ((x, Wk), (xd, Wd))
    expected = torch.autograd.grad(oute, insd)
    for a, e in zip(torch.autograd.grad(out, ins), expected):
        assert torch.allclose(a.double(), e, atol=1e-4), (a.double() - e).abs().max()
    y, r = native.kernel_lanes(x.detach(), Wk, w, offs, src, pos, o, _NO_BIAS)  # no dx asked for
    out = (y * gy).sum() + ((r * gr).sum() if residual else 0)
    for a, e in zip(torch.autograd.grad(out, ins[1:]), expected[1:]):
        assert torch.allclose(a.double(), e, atol=1e-4), (a.double() - e).abs().max()


@pytestmark_lanes
def test_kernel_lanes_is_counted_as_kernel_product_and_refuses_malformed_arguments():
    from torch.utils.flop_counter import FlopCounterMode

    g = torch.Generator().manual_seed(14)
    offs, src = _csr(6, 20, 5, g)
    x = torch.randn(20, 4, 3, generator=g)
    Wk, w, pos = _coefficients(len(src), 3 * 8, g, True)
    with FlopCounterMode(display=False) as fc:
        native.kernel_lanes(x, Wk.detach(), w.detach(), offs, src, pos, 8, _NO_BIAS)
    assert fc.get_total_flops() == 2 * len(src) * 4 * 3 * (8 + 1)
    with pytest.raises(RuntimeError, match="c o"):
        native.kernel_lanes(x, Wk.detach(), w.detach(), offs, src, pos, 7, _NO_BIAS)
    with pytest.raises(RuntimeError, match="out of range"):
        native.kernel_lanes(x, Wk.detach(), w.detach(), offs, torch.full_like(src, 20), pos, 8, _NO_BIAS)


@pytestmark_lanes
@pytest.mark.parametrize("c_in,c_out,lanes", [(3, 8, True), (9, 8, True), (64, 8, True), (9, 32, True), (65, 8, False),
                                              (9, 33, False)])
def test_vcconv_runs_narrow_kernel_layers_in_lanes(c_in, c_out, lanes, monkeypatch):
    """The ``kernel`` order of a layer with at most ``KERNEL_LANES_MAX_IN`` input and ``KERNEL_LANES_MAX_OUT``
    output channels takes ``kernel_lanes``, a wider one ``kernel_product``; with lanes off the same layer
    agrees."""
    calls = _lanes_against_off(monkeypatch, "kernel_lanes", "KERNEL_LANES_MAX_IN", c_in, c_out, "down", "kernel",
                               lambda x, *rest: x.shape[2])
    assert calls == ([c_in] if lanes else [])


@pytestmark_lanes
def test_sum_forward_in_lanes_refuses_more_than_64_columns():
    """The lane path takes the kernels and the residual's weight in at most 4 vectors of 16; beyond
    that ``sum_product`` keeps the BLAS call (``lanes(65)`` is False) and the kernel refuses."""
    g = torch.Generator().manual_seed(3)
    offs, src = _csr(4, 6, 3, g)
    x = torch.randn(6, 8, generator=g)
    coef, w, pos = _coefficients(len(src), 64, g, True)
    with pytest.raises(RuntimeError, match="at most 63 kernels in lanes"):
        native._load().sum_forward(x, coef.detach(), w.detach(), offs, src, pos, True)
    assert not native.lanes(65)
    T, r = native.sum_product(x, coef, w, offs, src, pos)  # on the BLAS call
    Te, re = _naive_sum(*_double(x, coef, w), offs, src, pos)
    assert torch.allclose(T.double(), Te, atol=1e-5) and torch.allclose(r.double(), re, atol=1e-5)


def _mkl_max_threads():
    """MKL's thread count for the calling thread (its local setting where one is made), or None where
    libtorch has no MKL."""
    import ctypes
    from pathlib import Path

    lib = Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"
    try:
        get = ctypes.CDLL(str(lib)).MKL_Get_Max_Threads
    except (OSError, AttributeError):
        return None
    get.restype = ctypes.c_int
    return get()


@pytestmark_native
def test_the_kernels_leave_mkls_thread_count_as_they_found_it(torch_threads):
    """Each native parallel loop gives its threads one BLAS thread (fwk_native.h, ``OneBlasThread``) and
    puts the caller's setting back: the calling thread is one of the loop's, so a setting left behind
    would run torch's own products on it with one thread from then on."""
    if _mkl_max_threads() is None:
        pytest.skip("libtorch without MKL: the guard sets nothing")
    torch.set_num_threads(2)
    assert _mkl_max_threads() == 2
    g = torch.Generator().manual_seed(3)
    offs, src = _csr(40, 60, 6, g)
    x = torch.randn(60, 16 * 3, generator=g, requires_grad=True)
    Wk, w, pos = _coefficients(len(src), 3 * 8, g, True)
    y, r = native.kernel_product(x, Wk, w, offs, src, pos, 16, 3, 8)  # a BLAS product per output vertex
    (y.sum() + r.sum()).backward()
    assert _mkl_max_threads() == 2
    torch.set_num_threads(1)
    native.kernel_product(x, Wk, w, offs, src, pos, 16, 3, 8)
    assert _mkl_max_threads() == 1


@pytestmark_lanes
@pytest.mark.parametrize("b", [16, 5, 20])
def test_the_lane_kernels_add_the_bias_as_the_result_leaves_the_lanes(b, torch_threads):
    """``basis_lanes`` and ``kernel_lanes`` with a bias: the result without one plus the bias (no pass of its own),
    the bias's gradient the sum of the result's over vertices and batch, the other gradients unchanged; a bias of
    the wrong length is refused."""
    torch.set_num_threads(2)
    g = torch.Generator().manual_seed(21)
    c, o, M = 6, 5, 9
    offs, dst = _csr(13, 40, 9, g, empty=(2,))
    x = torch.randn(13, b, c, generator=g, requires_grad=True)
    basis = torch.randn(M, c, o, generator=g, requires_grad=True)
    coef, _, pos = _coefficients(len(dst), M, g, True)  # its residual weights drawn, not used: basis_lanes has none
    bias = torch.randn(o, generator=g, requires_grad=True)
    offs_o, src = _csr(11, 13, 9, g, empty=(3,))
    Wk, wo, pos_o = _coefficients(len(src), c * o, g, True)
    for call in (lambda bb: native.basis_lanes(x, basis, coef, offs, dst, pos, 40, bb),
                 lambda bb: native.kernel_lanes(x, Wk, wo, offs_o, src, pos_o, o, bb)[0]):
        y, y0 = call(bias), call(_NO_BIAS)
        assert torch.allclose(y, y0 + bias, atol=1e-5)
        gy = torch.randn(y.shape, generator=g)
        ins = (x, bias)
        got = torch.autograd.grad((y * gy).sum(), ins)
        (dx0,) = torch.autograd.grad((y0 * gy).sum(), (x,))
        assert torch.allclose(got[0], dx0, atol=1e-5)
        assert torch.allclose(got[1], gy.sum((0, 1)), atol=1e-4)
        with pytest.raises(RuntimeError, match="bias"):
            call(torch.randn(o + 1))


def test_basis_lanes_takes_the_cheaper_forward_route():
    """``lanes_forward_route``: each slot's kernel where c o <= 64 and its multiply-adds, at their price, are fewer
    (the chapter 5 width's 8 -> 3 layer); Z_j otherwise (its 16 -> 8 and 32 -> 16 layers, c o > 64; input vertices
    held by very many slots)."""
    assert native.lanes_forward_route(3089, 59623, 16, 8, 3, 35) == 2
    assert native.lanes_forward_route(631, 19190, 16, 16, 8, 35) == 1
    assert native.lanes_forward_route(106, 4342, 16, 32, 16, 35) == 1
    # Z_j is made once an input vertex: with 1,000 slots each, it is the cheaper
    assert native.lanes_forward_route(10, 10_000, 16, 8, 3, 35) == 1


def _elu_mix_double(t, res, a):
    """res + a ELU(t), ELU(t) and the gradient's factor a ELU'(t), in float64 (res None: ELU(t), ELU(t), ELU'(t))."""
    t = t.double()
    e = torch.where(t > 0, t, torch.expm1(t))
    d = torch.where(t > 0, torch.ones_like(t), torch.exp(t))
    return (e if res is None else res.double() + a * e), e, (d if res is None else a * d)


@pytestmark_lanes
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("residual", [True, False])
@pytest.mark.parametrize("shape", [(37, 5, 8), (16,), (3089, 16, 8), (3, 1, 1)])
def test_elu_mix_is_the_residual_blocks_activation_and_mix_within_an_ulp(shape, residual, threads, torch_threads):
    """res + a ELU(t) (ELU(t) without res) against float64: within 2 float32 ulps of the terms' sizes (Cephes'
    polynomial for e^t, about 1 ulp); t's gradient a g ELU'(t) alike, res's the upstream gradient itself."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(5)
    t = (3 * torch.randn(shape, generator=g)).requires_grad_()
    res = torch.randn(shape, generator=g).requires_grad_() if residual else None
    a = 0.7071
    y = native.elu_mix(t, res if residual else torch.empty(0), a, True, False)
    y64, e64, d64 = _elu_mix_double(t.detach(), None if res is None else res.detach(), a)
    eps = torch.finfo(torch.float32).eps
    scale = (e64.abs() if res is None else res.detach().abs().double() + a * e64.abs()) + torch.finfo(torch.float32).tiny
    assert bool(((y.double() - y64).abs() <= 2 * eps * scale).all())
    dy = torch.randn(shape, generator=g)
    grads = torch.autograd.grad(y, (t, res) if residual else (t,), dy)
    ref = dy.double() * d64
    assert bool(((grads[0].double() - ref).abs() <= 3 * eps * ref.abs() + torch.finfo(torch.float32).tiny).all())
    if residual:
        assert torch.equal(grads[1], dy)


@pytestmark_lanes
def test_elu_mix_at_the_edges_is_torchs_elu():
    """Large negative inputs give -1 (gradient 0 after e^-88), zeros and tiny values their own ELU, NaN stays NaN,
    infinities as torch's ELU."""
    t = torch.tensor([-1e4, -100., -88., -87., -10., -1., -0.3466, -0.34, -1e-3, -1e-6, -1e-30, -0., 0., 1e-30, 1.,
                      float("nan"), float("inf"), float("-inf")])
    y = native.elu_mix(t, torch.empty(0), 1.0, True, False)
    torch.testing.assert_close(y, torch.nn.functional.elu(t), rtol=2 * torch.finfo(torch.float32).eps, atol=0,
                               equal_nan=True)
    tt = t.clone().requires_grad_()
    (d,) = torch.autograd.grad(native.elu_mix(tt, torch.empty(0), 1.0, True, False).sum(), tt)
    tt0 = t.clone().requires_grad_()
    (d0,) = torch.autograd.grad(torch.nn.functional.elu(tt0).sum(), tt0)
    torch.testing.assert_close(d, d0, rtol=2 * torch.finfo(torch.float32).eps, atol=1e-37, equal_nan=True)


@pytestmark_lanes
@pytest.mark.parametrize("residual", [True, False])
def test_elu_mix_without_elu_is_torchs_add(residual):
    """``elu=False`` (a network's last layer): res + a t as torch's add with alpha (one multiply-add, within an ulp;
    t itself without res), the gradients a g and g."""
    g = torch.Generator().manual_seed(6)
    t = torch.randn(301, 16, 3, generator=g).requires_grad_()
    res = torch.randn(301, 16, 3, generator=g).requires_grad_() if residual else None
    a = 0.7071
    y = native.elu_mix(t, res if residual else torch.empty(0), a, False, False)
    eps = torch.finfo(torch.float32).eps
    if residual:
        torch.testing.assert_close(y, torch.add(res, t, alpha=a), rtol=eps, atol=1e-37)
    else:
        assert torch.equal(y, t)
    dy = torch.randn(301, 16, 3, generator=g)
    grads = torch.autograd.grad(y, (t, res) if residual else (t,), dy)
    torch.testing.assert_close(grads[0], (a if residual else 1.0) * dy, rtol=eps, atol=1e-37)
    if residual:
        assert torch.equal(grads[1], dy)


@pytestmark_lanes
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("elu", [True, False])
@pytest.mark.parametrize("residual", [True, False])
@pytest.mark.parametrize("shape", [(37, 5, 3), (300, 16, 3), (4, 1, 20), (700, 3, 1)])
def test_elu_mix_lays_its_result_out_batch_major_with_the_same_bits(shape, elu, residual, threads, torch_threads):
    """``batch_major``: the vertex-major result's values bit for bit, laid out (b, n, c) (its transposed view
    contiguous); the gradients from the loss's batch-major gradient (arriving through the transpose) the same bits
    as from that gradient made contiguous, contiguous themselves, res's in t's layout; a gradient in a third layout
    (a slice) is taken as well."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(7)
    n, b, c = shape
    t = (3 * torch.randn(shape, generator=g)).requires_grad_()
    res = torch.randn(shape, generator=g).requires_grad_() if residual else None
    inputs = (t, res) if residual else (t,)
    args = (t, res if residual else torch.empty(0), 0.7071, elu)
    y0, y1 = native.elu_mix(*args, False), native.elu_mix(*args, True)
    assert y1.shape == y0.shape and y1.stride() == (c, n * c, 1) and y1.transpose(0, 1).is_contiguous()
    assert torch.equal(y0, y1)
    up = torch.randn(b, n, c, generator=g)  # the loss's gradient of the (b, n, c) result
    want = torch.autograd.grad(y0, inputs, up.transpose(0, 1).contiguous(), retain_graph=True)
    got = torch.autograd.grad((y1.transpose(0, 1) * up).sum(), inputs)  # y1's gradient: up's transposed view
    for w_, g_ in zip(want, got):
        assert g_.is_contiguous() and torch.equal(w_, g_)
    sliced = torch.randn(n, b, 2 * c, generator=g)[..., ::2]
    got = torch.autograd.grad(native.elu_mix(*args, True), inputs, sliced)
    want = torch.autograd.grad(y0, inputs, sliced.contiguous())
    for w_, g_ in zip(want, got):
        assert torch.equal(w_, g_)


@pytestmark_lanes
@pytest.mark.parametrize("mode", ["up", "down"])
def test_a_last_layer_hands_on_its_result_batch_major(mode, monkeypatch):
    """A layer without an activation (the last of fwk's encoders and decoders) ends in ``elu_mix``'s identity mix,
    laid out batch-major: the (b, n, c) result it hands on is contiguous, and it agrees with the same layer on
    torch's code (``FWK_VCCONV_NATIVE=0``) in value and in the gradients of the input and every parameter; a layer
    with ELU hands on a vertex-major result as before."""
    from fwk.plugins import get_registry
    from fwk.testing.sampler import two_components

    h = get_registry().get("sampler", "simple")(levels=3).build(two_components())
    for act in (None, torch.nn.ELU()):
        torch.manual_seed(0)
        conv = get_registry().get("conv", "vcconv")(6, 3, h, 1, weight_num=5, mode=mode, residual_rate=0.5,
                                                    activation=act)
        x = torch.randn(4, conv.n_in, 6, requires_grad=True)
        runs = []
        for off in (False, True):
            if off:
                monkeypatch.setenv("FWK_VCCONV_NATIVE", "0")
            y = conv(x)
            if not off:
                assert y.is_contiguous() == (act is None)
            runs.append((y, *torch.autograd.grad(y.square().sum(), [x, *conv.parameters()])))
        monkeypatch.delenv("FWK_VCCONV_NATIVE")
        for a, e in zip(*runs):
            assert (a - e).abs().max() <= 1e-5 * (1 + e.abs().max())


def test_vcconv_fuses_only_torchs_elu_with_alpha_one():
    """``native.elu_mix`` stands in for torch's ELU (alpha 1, not in place) only: another activation, alpha or
    none keeps torch's modules."""
    import fwk_vcconv

    lanes = native.available() and native.lanes()
    assert fwk_vcconv._fused_elu(torch.nn.ELU()) == lanes
    for act in (None, torch.nn.ELU(alpha=0.5), torch.nn.ELU(inplace=True), torch.nn.ReLU(), torch.nn.CELU()):
        assert not fwk_vcconv._fused_elu(act)
