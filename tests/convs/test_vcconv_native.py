"""vcconv's native kernels (``fwk_vcconv.native``) against per-vertex loops in float64, in value
and gradient; their thread behaviour; their refusals; their multiply-add count. The whole conv on
the native path against the naive sum is ``tests/autoencoders/test_vcconv_naive.py`` (run with
the kernels and without)."""
import os

import pytest
import torch

from fwk_vcconv import native


@pytest.fixture
def torch_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def test_the_native_kernels_build():
    """CI has a compiler (``.ci/run``): the kernels must build there, not fall back silently."""
    if not native.enabled():
        pytest.skip("FWK_VCCONV_NATIVE=0")
    assert native.available(), native._failed


pytestmark_native = pytest.mark.skipif(not native.available(), reason=f"native kernels unavailable: {native._failed}")


def _csr(n_rows, n_target, max_k, g, empty=(1,)):
    """Random supports: row r holds 0..max_k distinct targets (rows in ``empty`` hold none)."""
    offs, idx = [0], []
    for r in range(n_rows):
        k = 0 if r in empty else int(torch.randint(1, max_k + 1, (1,), generator=g))
        idx += torch.randperm(n_target, generator=g)[:k].tolist()
        offs.append(len(idx))
    return torch.tensor(offs), torch.tensor(idx, dtype=torch.long)


def _naive_sum(x, A, offs, src, M):
    T, r = [], []
    for i in range(len(offs) - 1):
        X = x[src[offs[i]:offs[i + 1]]]  # (K, B)
        Ai = A[offs[i]:offs[i + 1]]
        T.append(X.T @ Ai[:, :M])
        if A.shape[1] == M + 1:
            r.append(X.T @ Ai[:, M])
    return torch.stack(T), (torch.stack(r) if r else None)


def _naive_basis(Z, A, offs, dst, n_out):
    y = Z.new_zeros(n_out, Z.shape[1])
    for j in range(len(offs) - 1):
        for s in range(int(offs[j]), int(offs[j + 1])):
            y[dst[s]] = y[dst[s]] + Z[j] @ A[s]
    return y


def _grads(out, inputs, upstream):
    return torch.autograd.grad(out, inputs, upstream, allow_unused=True)


@pytestmark_native
@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
def test_sum_product_matches_the_loops_in_value_and_gradient(residual, threads, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    n_in, n_out, B, M = 23, 9, 12, 5
    offs, src = _csr(n_out, n_in, 6, g)
    x = torch.randn(n_in, B, generator=g, requires_grad=True)
    A = torch.randn(len(src), M + residual, generator=g, requires_grad=True)
    T, r = native.sum_product(x, A, offs, src, M)
    xd, Ad = x.detach().double().requires_grad_(), A.detach().double().requires_grad_()
    Te, re = _naive_sum(xd, Ad, offs, src, M)
    assert torch.allclose(T.double(), Te, atol=1e-5)
    assert (T[1] == 0).all(), "an empty support gives zeros"
    gT = torch.randn(T.shape, generator=g)
    if residual:
        assert torch.allclose(r.double(), re, atol=1e-5)
        gr = torch.randn(r.shape, generator=g)
        got, exp = _grads((T, r), (x, A), (gT, gr)), _grads((Te, re), (xd, Ad), (gT.double(), gr.double()))
    else:
        assert r.numel() == 0
        got, exp = _grads(T, (x, A), gT), _grads(Te, (xd, Ad), gT.double())
    for a, e in zip(got, exp):
        assert torch.allclose(a.double(), e, atol=1e-4)


@pytestmark_native
@pytest.mark.parametrize("threads", [1, 2])
def test_basis_product_matches_the_loops_in_value_and_gradient(threads, torch_threads):
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(1)
    n_in, n_out, B, M = 11, 30, 10, 4
    offs, dst = _csr(n_in, n_out, 7, g, empty=(2, 5))
    Z = torch.randn(n_in, B, M, generator=g, requires_grad=True)
    A = torch.randn(len(dst), M, generator=g, requires_grad=True)
    y = native.basis_product(Z, A, offs, dst, n_out)
    Zd, Ad = Z.detach().double().requires_grad_(), A.detach().double().requires_grad_()
    ye = _naive_basis(Zd, Ad, offs, dst, n_out)
    assert torch.allclose(y.double(), ye, atol=1e-5)
    gy = torch.randn(y.shape, generator=g)
    got, exp = _grads(y, (Z, A), gy), _grads(ye, (Zd, Ad), gy.double())
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
    A = torch.randn(len(dst), 7, generator=g)
    runs = []
    for _ in range(3):
        y = native.basis_product(Z, A, offs, dst, 150)
        (dZ,) = torch.autograd.grad(y, Z, torch.ones_like(y))
        runs.append((y, dZ))
    for y, dZ in runs[1:]:
        assert torch.equal(y, runs[0][0]) and torch.equal(dZ, runs[0][1])


@pytestmark_native
def test_malformed_supports_are_refused_not_read_out_of_bounds():
    x, A = torch.randn(4, 3), torch.randn(3, 2)
    with pytest.raises(RuntimeError, match="out of range"):
        native.sum_product(x, A, torch.tensor([0, 2, 3]), torch.tensor([0, 4, 1]), 2)
    with pytest.raises(RuntimeError, match="slot count"):
        native.sum_product(x, A, torch.tensor([0, 2, 2]), torch.tensor([0, 1, 1]), 2)
    with pytest.raises(RuntimeError, match="decrease"):
        native.basis_product(torch.randn(3, 3, 2), A, torch.tensor([0, 3, 2, 3]), torch.tensor([0, 1, 1]), 3)
    with pytest.raises(RuntimeError, match="Float"):
        native.sum_product(x.double(), A.double(), torch.tensor([0, 2, 3]), torch.tensor([0, 1, 1]), 2)


@pytestmark_native
def test_the_flop_counter_counts_the_kernels_multiply_adds():
    from torch.utils.flop_counter import FlopCounterMode

    g = torch.Generator().manual_seed(3)
    offs, idx = _csr(8, 20, 5, g)
    x, A = torch.randn(20, 6, generator=g), torch.randn(len(idx), 4, generator=g)
    with FlopCounterMode(display=False) as fc:
        native.sum_product(x, A, offs, idx, 3)
        native.basis_product(torch.randn(8, 6, 4, generator=g), A, offs, idx, 20)
    assert fc.get_total_flops() == 2 * len(idx) * 6 * 4 * 2


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


def test_a_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path):
    import time

    lock = tmp_path / "lock"
    lock.write_text("")
    native._clear_stale_lock(tmp_path)
    assert lock.exists(), "a build running now keeps its lock"
    old = time.time() - native.STALE_LOCK_SECONDS - 60
    os.utime(lock, (old, old))
    native._clear_stale_lock(tmp_path)
    assert not lock.exists()
