"""benchmarks/decoder_signal.py: a layer's spread is its variation across codes relative to its
size; checked on decoders whose answers are known."""

import pytest
import torch
from torch import nn

from .scripts import load_benchmark


def _module():
    return load_benchmark("decoder_signal")


class Dec(nn.Module):
    """fc -> (conv, act) x 2 -> out, the layout of fwk's AE decoders."""

    def __init__(self, gain=1.0, bias=0.0):
        super().__init__()
        self.fc = nn.Linear(4, 6)
        self.convs = nn.ModuleList([nn.Linear(6, 6), nn.Linear(6, 6)])
        self.act = nn.Identity()
        self.out = nn.Linear(6, 3)
        with torch.no_grad():
            for c in self.convs:
                c.weight.copy_(gain * torch.eye(6))
                c.bias.fill_(bias)

    def forward(self, z):
        x = self.fc(z)
        for c in self.convs:
            x = self.act(c(x))
        return self.out(x)


def test_spreads_follow_the_signal():
    mod = _module()
    z = torch.randn(64, 4, generator=torch.Generator().manual_seed(0))
    d = Dec()
    with torch.no_grad():
        d.fc.bias.zero_()
        d.out.bias.zero_()
    s = mod.spreads(d, z)
    assert list(s) == ["fc", "conv0", "conv1", "out"]
    # identity convs: the same relative spread all the way
    assert s["conv0"] == pytest.approx(s["fc"], rel=1e-6) and s["conv1"] == pytest.approx(s["fc"], rel=1e-6)
    # a naive reference: std across codes over mean |activation|
    a = d.fc(z).detach()
    assert s["fc"] == pytest.approx((a.std(0).mean() / a.abs().mean()).item(), rel=1e-6)
    # convs that shrink the code's part and add a constant: the spread falls layer by layer
    s2 = mod.spreads(Dec(gain=0.1, bias=1.0), z)
    assert s2["fc"] > s2["conv0"] > s2["conv1"]


def test_redrawn_copy_is_fresh_and_grad_norms_are_finite():
    mod = _module()
    d = Dec()
    f = mod.redrawn(d, 0)
    assert not torch.equal(f.convs[0].weight, d.convs[0].weight)  # the identity was re-drawn
    assert torch.equal(d.convs[0].weight, torch.eye(6))  # the original is untouched
    assert torch.equal(mod.redrawn(d, 0).fc.weight, f.fc.weight)  # seeded
    g1, g2 = mod.grad_norms(f, torch.randn(8, 4), 0)
    assert g1 > 0 and g2 > 0


def test_redrawn_lets_a_module_have_the_last_word_over_its_children():
    """A module whose reset_parameters re-draws a child and then rescales it (the feast conv's
    init: variance) keeps its scaling in the re-drawn copy."""

    class Scaled(nn.Module):
        def __init__(self):
            super().__init__()
            self.lin = nn.Linear(6, 6)
            self.reset_parameters()

        def reset_parameters(self):
            self.lin.reset_parameters()
            with torch.no_grad():
                self.lin.weight.mul_(100.0)

    d = Dec()
    d.convs[0] = Scaled()
    f = _module().redrawn(d, 0)
    bound = 100.0 / 6 ** 0.5  # nn.Linear draws within 1/sqrt(fan_in)
    assert f.convs[0].lin.weight.abs().max() > 0.2 * bound
    assert f.convs[0].lin.weight.abs().max() <= bound
