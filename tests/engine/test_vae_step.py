"""The shared (variational) autoencoder training step of fwk.engine against naive references."""
import torch
from torch import nn

from fwk.engine import autoencoder_module, kl_divergence, reparameterize


def test_kl_matches_torch_distributions():
    torch.manual_seed(0)
    mu, logvar = torch.randn(5, 7), torch.randn(5, 7) * 0.5
    q = torch.distributions.Normal(mu, torch.exp(0.5 * logvar))
    p = torch.distributions.Normal(torch.zeros_like(mu), torch.ones_like(mu))
    expect = torch.distributions.kl_divergence(q, p).sum(1).mean()
    assert torch.allclose(kl_divergence(mu, logvar), expect, atol=1e-6)
    assert kl_divergence(torch.zeros(3, 4), torch.zeros(3, 4)).item() == 0.0
    assert kl_divergence(mu, None).item() == 0.0


def test_reparameterize_samples_only_when_asked():
    mu, logvar = torch.randn(4000, 2), torch.full((4000, 2), 2 * torch.log(torch.tensor(3.0)).item())
    assert torch.equal(reparameterize(mu, logvar, False), mu)
    assert torch.equal(reparameterize(mu, None, True), mu)
    torch.manual_seed(1)
    z = reparameterize(mu, logvar, True)
    assert abs((z - mu).std().item() - 3.0) < 0.15


class _Lin(nn.Module):
    def __init__(self, variational):
        super().__init__()
        self.enc, self.dec = nn.Linear(6, 2), nn.Linear(2, 6)
        self.lv = nn.Linear(6, 2) if variational else None


def _step(variational, training):
    torch.manual_seed(2)
    net = _Lin(variational)
    unscale = lambda F: 3.0 * F + 1.0  # noqa: E731
    enc = lambda n, F: (n.enc(F), n.lv(F) if n.lv is not None else None)  # noqa: E731
    m = autoencoder_module(net, unscale, kl_weight=0.5, encode=enc)
    m.log = lambda *a, **k: None
    m.train(training)
    F = torch.randn(4, 6)
    torch.manual_seed(3)
    loss = m.loss((F,), "train")
    # naive: the same draws, written out
    torch.manual_seed(3)
    mu = net.enc(F)
    lv = net.lv(F) if variational else None
    z = mu + torch.randn_like(mu) * torch.exp(0.5 * lv) if (variational and training) else mu
    expect = (unscale(net.dec(z)) - unscale(F)).abs().mean()
    if variational:
        expect = expect + 0.5 * (-0.5 * (1 + lv - mu ** 2 - lv.exp()).sum(1).mean())
    return loss, expect


def test_autoencoder_module_loss_is_unscaled_l1_plus_weighted_kl():
    for variational in (False, True):
        for training in (False, True):
            loss, expect = _step(variational, training)
            assert torch.allclose(loss, expect, atol=1e-6), (variational, training)
