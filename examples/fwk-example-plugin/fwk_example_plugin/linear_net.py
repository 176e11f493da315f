r"""An example third-party model: a linear (variational) autoencoder that lends its networks to
other models, model ``linear-net`` (the network-factory role, ``fwk.protocols.NetworkFactory``).

Features F (b, n, c) of a representation are flattened vertex-major to f in R^{nc}
(entry v c + j is channel j of vertex v) and mapped by one affine layer each way:

    encoder:  mu = W_mu f + b_mu,      log sigma^2 = W_lv f + b_lv  (only when ``variational``)
    decoder:  F' = reshape(W_d z + b_d, (n, c))

with no hidden layer and no activation: a linear autoencoder, whose optimum under a squared
loss spans the principal subspace of the features (Baldi & Hornik 1989, "Neural networks and
principal component analysis: learning from examples without local minima"); with
``variational`` it is the linear VAE (Kingma & Welling 2014, "Auto-Encoding Variational Bayes"),
z = mu + sigma eps, trained with the KL term KL(N(mu, sigma^2) || N(0, I)) weighted by
``kl_weight`` (thesis eqs. 3.20-3.22). A model that borrows these networks (``dsm``, ``pb``,
``pbs``: ``network: {name: linear-net, latent: 16}``) trains them with its own loss.

The decoder reads (``build_decoder``):

* its own code, d = ``latent``;
* ``latent_parts = [d_0, d_1, ...]`` (Deep Spectral Meshes' Z = [z_0 | z_1 | ...]): the codes
  concatenated, d = sum d_j. A flat code is one latent vertex, so the decoder's one linear layer
  reads the concatenation (every entry of every part reaches the output);
* ``latent_in = d``: a foreign flat code of d entries (pb's code with a one-hot condition),
  through the same one linear layer.

As a model of its own (``fwk run`` with ``task: reconstruct``) it is a linear (V)AE trained on
one representation's features (default ``euclidean``) with the thesis's loss: the L1 norm in the
representation's unscaled space (+ the weighted KL when variational; ``fwk.engine``'s
``autoencoder_module``). It then plays ``ReconstructionModel`` and ``GenerativeModel`` (encode:
the posterior mean; ``sample`` decodes z ~ N(0, I)), as the built-in ``ae`` / ``vae`` do.

Registered through this package's own entry point (``example-linear-net``).
"""
from __future__ import annotations

from typing import Annotated

import numpy as np
import torch
from torch import nn

from fwk import engine
from fwk.data import Template
from fwk.engine import TrainConfig
from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT
from fwk.recipes import Kind, Spec, make_spec


class LinearEncoder(nn.Module):
    """(b, n, c) -> (mu (b, latent), log-variance (b, latent) or None): one affine map of the
    flattened features per output."""

    def __init__(self, n_vertices: int, channels: int, latent: int, variational: bool):
        super().__init__()
        self.n_vertices, self.channels = int(n_vertices), int(channels)
        self.mu = nn.Linear(self.n_vertices * self.channels, latent)
        self.logvar = nn.Linear(self.n_vertices * self.channels, latent) if variational else None

    def forward(self, x):
        if x.shape[1:] != (self.n_vertices, self.channels):
            raise DataError(f"linear-net encoder: input of shape {tuple(x.shape)}, built for "
                            f"(b, {self.n_vertices}, {self.channels})")
        h = x.flatten(1)
        return self.mu(h), (self.logvar(h) if self.logvar is not None else None)


class LinearDecoder(nn.Module):
    """(b, d) -> (b, n, c): one affine map, reshaped vertex-major."""

    def __init__(self, latent_in: int, n_vertices: int, channels: int):
        super().__init__()
        self.n_vertices, self.channels = int(n_vertices), int(channels)
        self.fc = nn.Linear(int(latent_in), self.n_vertices * self.channels)

    def forward(self, z):
        return self.fc(z).reshape(len(z), self.n_vertices, self.channels)


class _Net(nn.Module):
    """The encoder and decoder as one module (``enc``, ``dec``: the state_dict's key prefixes)."""

    def __init__(self, enc, dec):
        super().__init__()
        self.enc, self.dec = enc, dec


class LinearNet:
    r"""Linear (variational) autoencoder: one affine encoder and decoder of the flattened features, lent to dsm, pb and pbs.

    mu = W_mu vec(F) + b_mu (and log sigma^2 = W_lv vec(F) + b_lv when ``variational``);
    F' = reshape(W_d z + b_d). Weights drawn as ``torch.nn.Linear`` draws them (the model that
    builds the networks seeds torch first).

    Args:
        latent (int): the code's size (``latent_size``).
        variational (bool): the encoder also returns a log-variance (a VAE); else (mu, None).
        representation (representation): the features this model trains on as a model of its own
            (default ``euclidean``, std scaling); a model borrowing the networks uses its own.
        kl_weight (float | None): the KL weight when trained as a model of its own (default: the
            recipe's ``train.kl_weight``).
        train (dict | None): training settings overriding the recipe's ``train`` for this model.
    """

    name = "linear-net"
    task_family = RECONSTRUCT
    variational: bool = True  # the network-factory role's member, declared on the class; set per instance

    def __init__(self, latent: int = 16, variational: bool = True,
                 representation: Annotated[Spec, Kind("representation")] = "euclidean",
                 kl_weight: float | None = None, train: dict | None = None):
        if isinstance(latent, bool) or not isinstance(latent, int) or latent < 1:
            raise RecipeError(f"latent: expected an integer >= 1, got {latent!r}")
        if not isinstance(variational, bool):
            raise RecipeError(f"variational: expected true or false, got {variational!r}")
        if kl_weight is not None and not kl_weight >= 0:
            raise RecipeError(f"kl_weight: expected a number >= 0, got {kl_weight!r}")
        self.latent, self.variational = latent, variational
        self.representation = make_spec("representation", representation, "representation")
        self.kl_weight = kl_weight
        self.train_overrides = dict(train or {})
        TrainConfig().replace(**self.train_overrides)  # an unknown setting fails now, naming the key
        self.rep = self.net = None
        self.shape = None  # (n, c) of the features trained on

    @property
    def latent_size(self) -> int:
        """The size of the code z (``latent``)."""
        return self.latent

    # ------------------------------------------------------------------ the network-factory role
    def build_encoder(self, template, in_channels: int, ctx=None) -> nn.Module:
        """A module (b, n, in_channels) float32 -> (mu (b, latent), logvar (b, latent) or None);
        ``ctx`` is not needed (no graph hierarchy)."""
        return LinearEncoder(template.n_vertices, in_channels, self.latent, self.variational)

    def build_decoder(self, template, out_channels: int, ctx=None, latent_in: int | None = None,
                      latent_parts: list[int] | None = None) -> nn.Module:
        """A module (b, d) float32 -> (b, n, out_channels): d = ``latent`` by default, the sum of
        ``latent_parts`` (codes concatenated), or ``latent_in`` (a foreign flat code)."""
        if latent_in is not None and latent_parts is not None:
            raise RecipeError("build_decoder: give latent_in (a flat code) or latent_parts (codes concatenated), "
                              "not both")
        if latent_parts is not None:
            if not latent_parts or any(int(p) < 1 for p in latent_parts):
                raise RecipeError(f"latent_parts: expected positive code sizes, got {list(latent_parts)}")
            d = sum(int(p) for p in latent_parts)
        else:
            d = self.latent if latent_in is None else int(latent_in)
        return LinearDecoder(d, template.n_vertices, out_channels)

    # ------------------------------------------------------------------ the model roles
    def fit(self, data, ctx) -> None:
        """Train the linear (V)AE on the representation's features of ``data.stack("train")``
        (``fwk.engine.autoencoder_module``: unscaled L1 + kl_weight KL)."""
        self.rep, F, Fv = engine.fit_features(self.representation, data)
        self.shape = (int(F.shape[1]), int(F.shape[2]))
        self._template = data.template
        engine.seed_everything(ctx.seed)
        c = self.shape[1]
        self.net = _Net(self.build_encoder(data.template, c, ctx), self.build_decoder(data.template, c, ctx))
        config = ctx.train.replace(**self.train_overrides)
        kl = config.kl_weight if self.kl_weight is None else self.kl_weight
        engine.fit(engine.autoencoder_module(self.net, self.rep.unscale, kl), F, Fv, ctx, self.name, config)
        self.net.eval()

    def _check(self):
        if self.net is None:
            raise RuntimeError("linear-net: used as a model before fit() or load_state_dict()")

    @torch.no_grad()
    def encode(self, P) -> np.ndarray:
        """(b, n, 3) float64 -> (b, latent) float64: the (posterior mean) code."""
        self._check()
        mu, _ = self.net.enc(torch.as_tensor(self.rep.encode(np.asarray(P, dtype=np.float64))))
        return mu.numpy().astype(np.float64)

    @torch.no_grad()
    def decode(self, z, target=None) -> np.ndarray:
        """(b, latent) -> (b, n, 3) float64; ``target`` places outputs of a representation that
        loses the rigid placement (dr) onto it (see ``reconstruct``)."""
        self._check()
        G = self.net.dec(torch.as_tensor(np.atleast_2d(np.asarray(z)), dtype=torch.float32))
        return self.rep.decode(G.numpy(), None, target)

    def reconstruct(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, n, 3): decode the (posterior mean) code; dr outputs are registered
        to the input (thesis 3.3.10)."""
        return self.decode(self.encode(P), target=P)

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n meshes decoded from z ~ N(0, I) (NumPy's generator of ``seed``)."""
        return self.decode(np.random.default_rng(seed).standard_normal((n, self.latent)))

    def state_dict(self) -> dict:
        """The networks' tensors, the representation's state and plain data (fwk saves it as safetensors)."""
        self._check()
        return {"net": self.net.state_dict(), "rep": self.rep.state_dict(), "shape": list(self.shape),
                "template_vertices": self._template.vertices, "template_triangles": self._template.triangles}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a model trained on its own (``ctx`` is passed on to the representation)."""
        self.rep = self.representation.build()
        self.rep.load_state_dict(d["rep"], ctx)
        self.shape = (int(d["shape"][0]), int(d["shape"][1]))
        self._template = Template(np.asarray(d["template_vertices"]), np.asarray(d["template_triangles"]))
        c = self.shape[1]
        self.net = _Net(self.build_encoder(self._template, c, ctx), self.build_decoder(self._template, c, ctx))
        self.net.load_state_dict(d["net"])
        self.net.eval()


@hookimpl
def fwk_register_models():
    return [LinearNet]
