"""The variational pieces every (variational) autoencoder's loss uses (thesis eqs. 3.19-3.23)."""
from __future__ import annotations

import torch


def kl_divergence(mu, logvar):
    """KL(N(mu, diag exp(logvar)) || N(0, I)) = -1/2 sum_j (1 + logvar_j - mu_j^2 - exp(logvar_j)),
    averaged over the batch (thesis eq. 3.22); zero for a deterministic code (``logvar`` None)."""
    if logvar is None:
        return mu.new_zeros(())
    return -0.5 * torch.mean(torch.sum(1 + logvar - mu.pow(2) - logvar.exp(), dim=1))


def reparameterize(mu, logvar, sample: bool):
    """z = mu + sigma eps with eps ~ N(0, I) when ``sample`` (training a VAE), else the mean."""
    if not sample or logvar is None:
        return mu
    return mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
