"""fwk.native.ops (fwk's own kernels, ``core.cpp``): ``l1_mean`` against ``torch.abs(a - b).mean()``, in value
and gradient (the gradient float for float), on one and two threads, with its fallback to torch where the kernel
does not apply."""
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from fwk.native import ops

native = pytest.mark.skipif(not ops.CORE.available(), reason=f"fwk's native kernels unavailable: {ops.CORE.failed}")

SHAPES = [(16, 37, 3), (1, 1, 1), (33, 65, 8), (40, 3, 17), (70, 2, 5)]


def test_the_core_kernels_build():
    """CI has a compiler (``.ci/run``): the kernels must build there, not fall back silently."""
    if not ops.CORE.enabled():
        pytest.skip("FWK_CORE_NATIVE=0")
    assert ops.CORE.available(), ops.CORE.failed


def _torch_l1(a, b):
    return torch.abs(a - b).mean()


@native
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("shape", [*SHAPES, (16, 11248, 3), (7,)])
def test_l1_mean_is_torchs_loss_and_the_same_gradient_float_for_float(shape, threads, torch_threads):
    """The value within float32 rounding of the double sum; the gradient of a and of b the same floats as torch's
    (g / N sgn(a - b), with exact ties where a = b), for any upstream g."""
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(3)
    a = torch.randn(shape, generator=g)
    b = torch.randn(shape, generator=g)
    b.view(-1)[::5] = a.view(-1)[::5]  # ties: a zero gradient there
    a1, b1 = a.clone().requires_grad_(), b.clone().requires_grad_()
    a0, b0 = a.clone().requires_grad_(), b.clone().requires_grad_()
    l1, l0 = ops.l1_mean(a1, b1), _torch_l1(a0, b0)
    assert type(l1.grad_fn).__name__ == "fwk_l1_meanBackward" and l1.shape == ()
    exact = (a.double() - b.double()).abs().mean()
    assert abs(float(l1.detach()) - float(exact)) <= 2 * torch.finfo(torch.float32).eps * float(exact)
    assert torch.allclose(l1, l0, rtol=1e-5)
    w = 3.7
    assert all(torch.equal(p, q) for p, q in zip(torch.autograd.grad(w * l1, (a1, b1)),
                                                 torch.autograd.grad(w * l0, (a0, b0))))


@native
def test_l1_mean_is_the_same_bits_on_repeat_for_a_thread_count(torch_threads):
    torch.set_num_threads(2)
    a, b = torch.randn(16, 1000, 3), torch.randn(16, 1000, 3)
    assert torch.equal(ops.l1_mean(a, b), ops.l1_mean(a, b))


@native
def test_l1_mean_takes_strided_inputs_and_treats_nan_as_torch_does():
    """A NaN makes the loss NaN; its gradient there is 0, as torch's (sgn(NaN) = 0)."""
    g = torch.Generator().manual_seed(4)
    a = torch.randn(9, 16, 3, generator=g).transpose(0, 1).requires_grad_()
    b = torch.randn(16, 9, 3, generator=g)
    assert torch.allclose(ops.l1_mean(a, b), _torch_l1(a, b), rtol=1e-6)
    assert torch.equal(*(torch.autograd.grad(f(a, b), a)[0] for f in (ops.l1_mean, _torch_l1)))
    n = torch.randn(4, 5, generator=g)
    n[1, 2] = float("nan")
    n.requires_grad_()
    assert torch.isnan(ops.l1_mean(n, torch.zeros(4, 5)))
    d1, d0 = (torch.autograd.grad(f(n, torch.zeros(4, 5)), n)[0] for f in (ops.l1_mean, _torch_l1))
    torch.testing.assert_close(d1, d0, rtol=0, atol=0, equal_nan=True)


def test_l1_mean_is_torchs_expression_where_the_kernels_do_not_apply(monkeypatch):
    """Broadcasting, another dtype, autocast, no elements, the kernels off: torch's own expression, its value."""
    a, b = torch.randn(4, 3, requires_grad=True), torch.randn(3)
    cases = [(a, b), (a.double(), b.double()), (torch.zeros(0, 3), torch.zeros(0, 3))]
    for x, y in cases:
        torch.testing.assert_close(ops.l1_mean(x, y), _torch_l1(x, y), equal_nan=True, rtol=0, atol=0)
    assert "fwk" not in type(ops.l1_mean(a, b).grad_fn).__name__
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert "fwk" not in type(ops.l1_mean(a, torch.randn(4, 3)).grad_fn).__name__
    monkeypatch.setenv("FWK_CORE_NATIVE", "0")
    assert "fwk" not in type(ops.l1_mean(a, torch.randn(4, 3)).grad_fn).__name__


@native
def test_l1_mean_goes_through_the_dispatcher_where_something_intercepts_it():
    """Under a TorchDispatchMode (torch's flop counter) the call is the operator itself: it runs, gives the same
    value, and counts no flops (it is no product)."""
    a, b = torch.randn(8, 5, 3), torch.randn(8, 5, 3)
    with FlopCounterMode(display=False) as fc:
        l = ops.l1_mean(a, b)
    assert fc.get_total_flops() == 0
    assert torch.equal(l, ops.l1_mean(a, b))
