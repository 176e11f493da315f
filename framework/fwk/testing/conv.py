"""ConvContract: shapes, gradients, batch independence, determinism, 3 and 9 channels, CUDA."""
from __future__ import annotations

import pytest


class ConvContract:
    component: type = None
    params: dict = {}
    sampler: tuple = ("quadric", {"factors": [4]})

    def hierarchy(self):
        from fwk.plugins import get_registry
        from fwk.testing.sampler import two_components

        name, params = self.sampler
        return get_registry().get("sampler", name)(**params).build(two_components())

    def make(self, c_in, c_out, level=0, seed=0):
        import torch

        torch.manual_seed(seed)
        return self.component(c_in, c_out, self.hierarchy(), level, **self.params)

    @pytest.mark.parametrize("c_in", [3, 9])
    def test_shape_and_gradients(self, c_in):
        import torch

        h = self.hierarchy()
        for level in (0, 1):
            conv = self.make(c_in, 16, level)
            x = torch.randn(4, h.levels[level].n_vertices, c_in, requires_grad=True)
            y = conv(x)
            assert y.shape == (4, h.levels[level].n_vertices, 16)
            y.square().mean().backward()
            assert x.grad is not None and torch.isfinite(x.grad).all()
            assert all(p.grad is not None for p in conv.parameters())

    def test_batch_independence_and_determinism(self):
        import torch

        h = self.hierarchy()
        conv = self.make(3, 8)
        x = torch.randn(3, h.levels[0].n_vertices, 3)
        y = conv(x)
        x2 = x.clone()
        x2[1] += 1.0
        y2 = conv(x2)
        assert torch.allclose(y[0], y2[0]) and torch.allclose(y[2], y2[2])
        assert torch.allclose(self.make(3, 8, seed=0)(x), self.make(3, 8, seed=0)(x))

    def test_cuda_when_available(self):
        import torch

        if not torch.cuda.is_available():
            pytest.skip("no CUDA device on this machine")
        conv = self.make(3, 8).cuda()
        x = torch.randn(2, self.hierarchy().levels[0].n_vertices, 3, device="cuda")
        assert conv(x).is_cuda
