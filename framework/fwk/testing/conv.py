"""ConvContract: the conv role (``fwk.protocols.Conv``), shapes, gradients, batch independence,
determinism, ``reset_parameters``, 3 and 9 channels, CUDA against the CPU (where a device is);
the strided / transposed role when the class declares ``strided = True``; the fused pooling role
(``FusedPoolingConv``) when it declares ``fuses_pooling = True``; ``upgrade`` keeping today's
layout where the conv reads an earlier one (``UpgradesSavedTensors``).

Subclass it in a test module::

    from fwk.testing.conv import ConvContract

    class TestMyConv(ConvContract):
        component = MyConv                # the class
        params = {"k": 3}                 # its recipe parameters (kept small)
        sampler = ("quadric", {"factors": [4]})   # the hierarchy it is tested on (name, params)

The hierarchy is built by a registered sampler on ``fwk.testing.sampler.two_components()`` (two
icospheres: a template with two connected components).
"""
from __future__ import annotations

import pytest
import torch

from fwk.plugins import get_registry
from fwk.graph import sparse_apply, torch_sparse
from fwk.protocols import CONV_BUILD_ARGS, STRIDED_BUILD_ARGS, Conv, FusedPoolingConv, UpgradesSavedTensors, plays
from fwk.testing.sampler import two_components


class ConvContract:
    component: type = None
    params: dict = {}
    sampler: tuple = ("quadric", {"factors": [4]})  # name-ok: the suite's default hierarchy, a test parameter
    residual_rate: float = 0.5  # the rate the strided tests use besides None

    def hierarchy(self):
        name, params = self.sampler
        return get_registry().get("sampler", name)(**params).build(two_components())

    def make(self, c_in, c_out, level=0, seed=0, hierarchy=None, **extra):
        torch.manual_seed(seed)
        return self.component(c_in, c_out, hierarchy or self.hierarchy(), level, **{**self.params, **extra})

    def test_plays_the_conv_role(self):
        c = self.component
        assert plays(c, Conv), "a conv class defines name, build_args, strided, forward and reset_parameters"
        assert isinstance(c.name, str) and c.name
        assert isinstance(c.strided, bool), "strided: a class attribute, True or False"
        expect = CONV_BUILD_ARGS + (STRIDED_BUILD_ARGS if c.strided else ())
        assert tuple(c.build_args) == expect, f"the model supplies {expect}, not the recipe"
        assert (c.__doc__ or "").strip(), "the first docstring line is the `fwk list` summary"
        assert isinstance(self.make(3, 4), torch.nn.Module)

    def test_upgrade_keeps_todays_layout(self):
        """Where the conv reads saved tensors of an earlier layout (``UpgradesSavedTensors``): a
        tensor already in today's layout comes back unchanged, and its own state dict loads as it is."""
        conv = self.make(3, 4)
        if not isinstance(conv, UpgradesSavedTensors):
            pytest.skip(f"{self.component.name} reads no earlier layout (no upgrade)")
        for name, p in conv.named_parameters(recurse=False):
            assert torch.equal(conv.upgrade(name, p.detach()), p.detach()), name
        fresh = self.make(3, 4, seed=1)
        fresh.load_state_dict(conv.state_dict())
        assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), conv.state_dict().values()))

    @pytest.mark.parametrize("c_in", [3, 9])
    def test_shape_and_gradients(self, c_in):
        h = self.hierarchy()
        for level in (0, 1):
            conv = self.make(c_in, 16, level, hierarchy=h)
            x = torch.randn(4, h.levels[level].n_vertices, c_in, requires_grad=True)
            y = conv(x)
            assert y.shape == (4, h.levels[level].n_vertices, 16)
            y.square().mean().backward()
            assert x.grad is not None and torch.isfinite(x.grad).all()
            assert all(p.grad is not None for p in conv.parameters())

    def test_batch_independence_and_determinism(self):
        h = self.hierarchy()
        conv = self.make(3, 8, hierarchy=h)
        x = torch.randn(3, h.levels[0].n_vertices, 3)
        y = conv(x)
        x2 = x.clone()
        x2[1] += 1.0
        y2 = conv(x2)
        assert torch.allclose(y[0], y2[0]) and torch.allclose(y[2], y2[2])
        assert torch.allclose(self.make(3, 8, seed=0, hierarchy=h)(x), self.make(3, 8, seed=0, hierarchy=h)(x))

    def test_reset_parameters_redraws_every_parameter_deterministically(self):
        conv = self.make(3, 8)
        first = {k: v.detach().clone() for k, v in conv.named_parameters()}
        assert first, "a conv has parameters"
        torch.manual_seed(1)
        conv.reset_parameters()
        a = {k: v.detach().clone() for k, v in conv.named_parameters()}
        assert any(not torch.equal(first[k], a[k]) for k in a), "reset_parameters() draws new random values"
        with torch.no_grad():  # whatever the parameters hold, a reset under a seed gives the same state
            for p in conv.parameters():
                p.add_(1.0)
        torch.manual_seed(1)
        conv.reset_parameters()
        b = dict(conv.named_parameters())
        assert all(torch.equal(a[k], b[k]) for k in a), "reset_parameters() under a seed sets every parameter"

    # ---- the strided / transposed role (strided = True)
    def _strided(self):
        if not self.component.strided:
            pytest.skip(f"{self.component.name} does not play the strided role (strided = False)")

    @pytest.mark.parametrize("residual", [False, True])
    def test_strided_down_and_up_shapes_and_gradients(self, residual):
        self._strided()
        h = self.hierarchy()
        r = self.residual_rate if residual else None
        n0, n1 = h.levels[0].n_vertices, h.levels[1].n_vertices
        for mode, n_in, n_out, c_in, c_out in (("down", n0, n1, 3, 12), ("up", n1, n0, 12, 3), ("down", n0, n1, 6, 6)):
            conv = self.make(c_in, c_out, 0, hierarchy=h, mode=mode, residual_rate=r)
            x = torch.randn(2, n_in, c_in, requires_grad=True)
            y = conv(x)
            assert y.shape == (2, n_out, c_out), (mode, y.shape)
            y.square().mean().backward()
            assert x.grad is not None and torch.isfinite(x.grad).all()
            assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in conv.parameters())

    def test_strided_reset_and_batch_independence(self):
        self._strided()
        h = self.hierarchy()
        for mode, n_in in (("down", h.levels[0].n_vertices), ("up", h.levels[1].n_vertices)):
            conv = self.make(4, 5, 0, hierarchy=h, mode=mode, residual_rate=self.residual_rate)
            x = torch.randn(3, n_in, 4)
            y = conv(x)
            x2 = x.clone()
            x2[1] += 1.0
            assert torch.allclose(conv(x2)[0], y[0]) and torch.allclose(conv(x2)[2], y[2])
            torch.manual_seed(2)
            conv.reset_parameters()
            a = [p.detach().clone() for p in conv.parameters()]
            torch.manual_seed(2)
            conv.reset_parameters()
            assert all(torch.equal(p, q) for p, q in zip(a, conv.parameters()))

    # ---- the fused pooling role (FusedPoolingConv, fuses_pooling = True)
    @pytest.mark.parametrize("threads", [1, 2])
    def test_fused_pooling_equals_pooling_and_up_sampling_in_value_and_gradient(self, threads):
        """forward(x, rows=m) = D forward(x) for the suite sampler's selecting D (D[i, m_i] = 1),
        forward_up(x, U) = forward(U x), values and gradients (x and every parameter)."""
        if not (plays(self.component, FusedPoolingConv) and self.component.fuses_pooling):
            pytest.skip(f"{self.component.name} does not fuse pooling (fuses_pooling)")
        h = self.hierarchy()
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            for level in range(len(h.down)):
                D, U = torch_sparse(h.down[level]).coalesce(), torch_sparse(h.up[level])
                r, kept = D.indices()
                if not (torch.equal(r, torch.arange(D.shape[0])) and bool((D.values() == 1).all())):
                    pytest.skip("the suite's sampler does not select vertices: set `sampler` to one that does")
                conv = self.make(6, 5, level, hierarchy=h)
                with torch.no_grad():
                    for p in conv.parameters():  # a non-zero bias, whatever the initialisation
                        p.add_(0.1 * torch.randn_like(p))
                pairs = ((lambda v: conv(v, rows=kept), lambda v: sparse_apply(D, conv(v)), h.levels[level].n_vertices),
                         (lambda v: conv.forward_up(v, U), lambda v: conv(sparse_apply(U, v)), h.levels[level + 1].n_vertices))
                for fused, plain, n_in in pairs:
                    x = torch.randn(3, n_in, 6, requires_grad=True)
                    y = fused(x)
                    g = torch.randn_like(y)
                    got = torch.autograd.grad((y * g).sum(), [x, *conv.parameters()])
                    e = plain(x)
                    ref = torch.autograd.grad((e * g).sum(), [x, *conv.parameters()])
                    assert y.shape == e.shape and (y - e).abs().max() <= 1e-5 * (1 + e.abs().max())
                    for a, b in zip(got, ref):
                        assert (a - b).abs().max() <= 1e-5 * (1 + b.abs().max())
        finally:
            torch.set_num_threads(before)

    def test_cuda_matches_cpu_when_available(self):
        """On a CUDA device the conv gives the CPU's values and gradients (x and every parameter):
        plain on levels 0 and 1, strided down and up where it plays that role, fused pooling
        where it fuses; and a bfloat16 autocast pass there is finite and near float32's."""
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device on this machine")
        h = self.hierarchy()
        n = [lv.n_vertices for lv in h.levels]
        cases = [(self.make(3, 8, level, hierarchy=h), (lambda c: c), n[level], 3) for level in (0, 1)]
        if self.component.strided:
            for mode, n_in, c_in, c_out in (("down", n[0], 3, 12), ("up", n[1], 12, 3)):
                conv = self.make(c_in, c_out, 0, hierarchy=h, mode=mode, residual_rate=self.residual_rate)
                cases.append((conv, (lambda c: c), n_in, c_in))
        if plays(self.component, FusedPoolingConv) and self.component.fuses_pooling:
            D, U = torch_sparse(h.down[0]).coalesce(), torch_sparse(h.up[0])
            kept = D.indices()[1]
            conv = self.make(6, 5, 0, hierarchy=h)
            on = lambda c, t: t.to(next(c.parameters()).device)  # the model hands them on its device
            cases.append((conv, (lambda c, kept=kept: lambda v: c(v, rows=on(c, kept))), n[0], 6))
            cases.append((conv, (lambda c, U=U: lambda v: c.forward_up(v, on(c, U))), n[1], 6))
        for conv, call, n_in, c_in in cases:
            assert_cuda_matches_cpu(conv, call, torch.randn(2, n_in, c_in))


def assert_cuda_matches_cpu(module: torch.nn.Module, call, x: torch.Tensor, rtol: float = 1e-4,
                            device: str = "cuda") -> None:
    """``call(module)(x)`` on the CPU and on a copy of ``module`` moved to CUDA agree in value and
    in the gradients of x and of every parameter (a random cotangent; rtol of each tensor's largest
    magnitude); under bfloat16 autocast on CUDA the output is finite and within 5 % of float32's
    scale. ``call(m)`` returns the function of x to test (``lambda m: m`` for ``m(x)``); ``device``:
    the other device (``cpu`` checks the check itself where no GPU is)."""
    import copy

    with torch.no_grad():  # non-zero biases and non-trivial weights, whatever the initialisation
        for p in module.parameters():
            p.add_(0.1 * torch.randn_like(p))
    gpu = copy.deepcopy(module).to(device)
    outs, g = [], None
    for m, dev in ((module, "cpu"), (gpu, device)):
        xi = x.detach().to(dev).requires_grad_()
        y = call(m)(xi)
        if g is None:  # one cotangent for both devices
            g = torch.randn_like(y)
        got = torch.autograd.grad((y * g.to(dev)).sum(), [xi, *m.parameters()], allow_unused=True)
        outs.append([y.detach().cpu(), *[None if t is None else t.detach().cpu() for t in got]])
    for i, (a, b) in enumerate(zip(*outs)):
        assert (a is None) == (b is None), f"tensor {i}: a gradient on one device only"
        if a is not None:
            assert b.dtype == a.dtype and b.shape == a.shape, (i, a.dtype, b.dtype)
            err = (a - b).abs().max().item()
            assert err <= rtol * (1 + a.abs().max().item()), f"tensor {i} (0: the output, 1: x's gradient): {err:.3g}"
    with torch.autocast(device, dtype=torch.bfloat16):
        y16 = call(gpu)(x.to(device))
    y32 = outs[0][0]
    assert torch.isfinite(y16).all()
    assert (y16.float().cpu() - y32).abs().max().item() <= 0.05 * (1 + y32.abs().max().item())
