"""Model ``mlp-vae``: the fully connected mesh VAE (Tan et al. 2018, "Variational autoencoders
for deforming 3D mesh models"; cited by the thesis, 2.2).

The representation's features F (n x c, scaled) are flattened to a vector and encoded by a
multi-layer perceptron to the mean mu and log-variance log sigma^2 of q(z | F); z = mu + sigma
eps (eps ~ N(0, I)) is decoded by the mirrored perceptron. Loss (thesis table 3.2, eqs.
3.20-3.22): the L1 norm between the ground truth and the prediction in the representation's
own *unscaled* space (the scaling is undone differentiably), plus the weighted KL divergence
KL(q(z|F) || N(0, I)) = -1/2 sum(1 + log sigma^2 - mu^2 - sigma^2), weight ``kl_weight``.
Activations ELU (thesis 3.4). At inference the mean mu is decoded.

Plays ``fwk.protocols.ReconstructionModel`` and ``GenerativeModel`` (encode, decode, sample from
N(0, I)). The representation (default ``euclidean``, whose own default scaling is std) is a
recipe parameter.
"""
from __future__ import annotations

from typing import Annotated

import numpy as np
import torch
from torch import nn

from fwk.engine import TrainConfig, autoencoder_module, fit, fit_features, predict_batches, seed_everything
from fwk.errors import RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT
from fwk.recipes import Kind, Spec


def _mlp(sizes, last_act=False):
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or last_act:
            layers.append(nn.ELU())
    return nn.Sequential(*layers)


class _Net(torch.nn.Module):
    """Encoder MLP with mean and log-variance heads, and the mirrored decoder MLP."""

    def __init__(self, d_in, hidden, latent):
        super().__init__()
        self.enc = _mlp([d_in, *hidden], last_act=True)
        self.mu = nn.Linear(hidden[-1] if hidden else d_in, latent)
        self.logvar = nn.Linear(hidden[-1] if hidden else d_in, latent)
        self.dec = _mlp([latent, *reversed(hidden), d_in])

    def encode(self, x):
        h = self.enc(x.flatten(1))
        return self.mu(h), self.logvar(h)

    def decode(self, z, shape):
        return self.dec(z).reshape(len(z), *shape)


class MLPVAE:
    """Fully connected mesh VAE (Tan et al. 2018)."""

    name = "mlp-vae"
    task_family = RECONSTRUCT

    def __init__(self, latent: int = 64, hidden: list[int] | None = None,
                 representation: Annotated[Spec, Kind("representation")] = "euclidean",
                 kl_weight: float | None = None, train: dict | None = None):
        self.latent = latent
        self.hidden = list(hidden) if hidden else [512, 256]
        if latent < 1 or any(h < 1 for h in self.hidden):
            raise RecipeError(f"latent / hidden: sizes must be positive, got latent={latent}, hidden={self.hidden}")
        if kl_weight is not None and kl_weight < 0:
            raise RecipeError(f"kl_weight: must be >= 0, got {kl_weight}")
        self.representation = representation
        self.kl_weight = kl_weight
        self.train_overrides = dict(train or {})
        TrainConfig().replace(**self.train_overrides)  # unknown settings fail now, naming the key
        self.rep = self.net = None
        self.shape = None

    @property
    def latent_size(self) -> int:
        """The size of the code z."""
        return self.latent

    def fit(self, data, ctx) -> None:
        self.rep, F, Fv = fit_features(self.representation, data)
        self.shape = tuple(F.shape[1:])
        seed_everything(ctx.seed)
        self.net = _Net(int(np.prod(self.shape)), self.hidden, self.latent)
        config = ctx.train.replace(**self.train_overrides)
        kl = config.kl_weight if self.kl_weight is None else self.kl_weight
        shape = self.shape
        module = autoencoder_module(self.net, self.rep.unscale, kl, encode=lambda net, F: net.encode(F),
                                    decode=lambda net, z: net.decode(z, shape))
        fit(module, F, Fv, ctx, self.name, config)
        self.net.cpu().eval()

    def _check(self):
        if self.net is None:
            raise RuntimeError("mlp-vae used before fit() or load_state_dict()")

    def encode(self, P) -> np.ndarray:
        """The posterior mean of q(z | P), (b, latent)."""
        self._check()
        self.net.eval()
        return predict_batches(lambda F: self.net.encode(F)[0], self.rep.encode(P), 256).astype(np.float64)

    def _features(self, z) -> np.ndarray:
        self._check()
        self.net.eval()
        return predict_batches(lambda x: self.net.decode(x, self.shape), np.asarray(z, dtype=np.float32), 256)

    def decode(self, z) -> np.ndarray:
        """(b, latent) codes -> (b, n, 3) positions."""
        return self.rep.decode(self._features(z))

    def reconstruct(self, P) -> np.ndarray:
        """Decode the posterior mean; representations that lose position (dr) are registered
        to the input, the thesis's evaluation protocol for DR outputs (3.3.10)."""
        return self.rep.decode(self._features(self.encode(P)), None, P)

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """Decode n codes drawn from N(0, I) (deterministic for a seed)."""
        z = np.random.default_rng(seed).standard_normal((n, self.latent))
        return self.decode(z)

    def state_dict(self) -> dict:
        return {"net": self.net.state_dict(), "rep": self.rep.state_dict(), "shape": self.shape,
                "latent": self.latent, "hidden": self.hidden}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a ``state_dict`` (``ctx`` is passed on to the representation)."""
        self.rep = self.representation.build()
        self.rep.load_state_dict(d["rep"], ctx)
        self.shape, self.latent, self.hidden = tuple(d["shape"]), int(d["latent"]), list(d["hidden"])
        self.net = _Net(int(np.prod(self.shape)), self.hidden, self.latent)
        self.net.load_state_dict(d["net"])
        self.net.eval()


@hookimpl
def fwk_register_models():
    return [MLPVAE]
