"""Models ``ae`` and ``vae``: graph (variational) autoencoders composed from a recipe
(thesis 3.3, 3.4, appendix A; CoMA / SpiralNet++ / Neural 3DMM / FeaStNet / LSA-3DMM layout).

A sampler builds the template's hierarchy once (levels 0..L, sparse down D_i and up U_i). With
channels [c_0 = |f|, c_1, ..., c_L]:

    encoder:  for i in 0..L-1:  x <- D_i ELU(conv_i(x))          (level i -> i+1)
              z = Linear(flatten(x))                             (ae)   or  mu, log sigma^2 (vae)
    decoder:  x = Linear(z) reshaped to (n_L, c_L)
              for i in L-1..0:  x <- ELU(conv'_i(U_i x))           (level i+1 -> i; c_{i+2} -> c_{i+1})
              out = conv_out(x)                                   (level 0, c_0 channels, no activation)

Each conv is built by the recipe's ``conv`` component at its level (``Cls(c_in, c_out, hierarchy,
level, **params)``), so any registered conv plugs in. Horizontal blocks at one level share the
level's operators (one hierarchy per template, cached). Losses (thesis table 3.2, eqs. 3.19-3.23):
the L1 norm in the representation's own unscaled space, plus ``kl_weight`` x KL for ``vae``.
Thesis defaults: channels [|f|, 16, 32, 64, 128], pooling factor 4, latent 64, ELU.

``fully_convolutional: true`` builds Zhou et al.'s fully convolutional layout instead (the
thesis's vcconv VAE: ``conv: vcconv``, ``sampler: {name: simple, levels: 4}``, channels
[|f|, 32, 64, 128, 128, 8], ``latent_vertices: 8``, residual rate 0.5): each encoder level is a
strided convolution (mode ``down``) with a residual path, each decoder level a transposed one
(mode ``up``); no separate pooling. Each block is, as in the thesis (4.4.3) and Zhou et al.'s
reference code,

    y = sqrt(1 - r) ELU(conv(x)) + sqrt(r) res(x)             (the ELU on the conv branch only)

except the encoder's and the decoder's last blocks, which have no ELU. A conv playing the strided
role (``strided = True``: vcconv) does each step itself (built with ``mode``, ``residual_rate``
and ``activation``); any other conv is composed with the sampler's pooling
(``fwk_autoencoder.strided.PooledConv``: pool, then the conv on the new level, the same block).
Without ``latent_vertices`` the last level's features (flattened) meet the latent through linear
layers.
``latent_vertices: n`` (implies ``fully_convolutional``) makes the latent itself a graph level as in
the thesis (8 latent vertices x 8 features = 64): the sampler supplies levels 0..L-1 and the last
strided convolution maps onto a level of exactly n vertices (farthest-point centres, see
``fwk_autoencoder.latent``); z is the flattened (n, c_L) map, ``latent`` = n c_L, no linear layer.

Both play ``fwk.protocols.NetworkFactory`` for other models (Deep Spectral Meshes, personalised
blendshapes): ``m.build_encoder(template, in_channels, ctx)`` returns a module (b, n, c_in) ->
(mu, logvar) (logvar None for ``ae``: ``variational`` False); ``m.build_decoder(template,
out_channels, ctx, latent_in=None, latent_parts=None)`` a module (b, d) -> (b, n, c_out), d the
latent size, or ``latent_in`` (a foreign flat code, through a linear layer), or the sum of
``latent_parts`` (codes of networks with this latent layout, concatenated: with
``latent_vertices`` read as one latent map, channels concatenated per latent vertex, no dense
layer; see ``fwk_autoencoder.latent``). As models they play ``ReconstructionModel`` and
``GenerativeModel`` (encode, decode, sample from N(0, I)). The representation (default
``euclidean``, whose own default scaling is std) is a recipe parameter.
"""
from __future__ import annotations

from typing import Annotated

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from fwk.data import Template
from fwk.engine import autoencoder_module, fit, fit_features, seed_everything
from fwk.errors import RecipeError
from fwk.graph import sparse_apply, torch_sparse
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT, Conv, FusedPoolingConv, plays
from fwk.recipes import Kind, Spec
from fwk.registry import did_you_mean

from .checked import build_conv
from .latent import LatentConvDecoder, LatentConvEncoder, batch_major, with_latent_level
from .strided import strided_conv

ACTIVATIONS = {"elu": nn.ELU, "relu": nn.ReLU, "leaky_relu": nn.LeakyReLU}


class _Sparse(nn.Module):
    """A fixed sparse operator (kept as a buffer so ``.to(device)`` moves it)."""

    def __init__(self, M):
        super().__init__()
        self.register_buffer("M", torch_sparse(M))

    def forward(self, x):
        return sparse_apply(self.M, x)


def _fuses(conv) -> bool:
    """Whether a built conv computes a pooling or up-sampling with itself (``FusedPoolingConv``)."""
    return isinstance(conv, FusedPoolingConv) and conv.fuses_pooling


def selected_rows(M) -> np.ndarray | None:
    """The vertex each row of a down-sampling M keeps, if M selects (one entry per row, equal to
    1: D[i, m_i] = 1, e.g. quadric's), else None (M averages: pool, then nothing to fuse)."""
    M = sp.csr_matrix(M)
    if M.nnz != M.shape[0] or not (np.diff(M.indptr) == 1).all() or not (M.data == 1).all():
        return None
    return M.indices.astype(np.int64)


class Encoder(nn.Module):
    """Conv, activation and pooling per level, then a linear map to the latent (mu, logvar or None).

    Where the conv plays ``FusedPoolingConv`` and the pooling D selects vertices, a level is
    act(conv(x, rows=m)) = D act(conv(x)) (the activation acts per vertex): the conv is computed
    only at the vertices the pooling keeps (1/4 of them at factor 4), the same maths."""

    def __init__(self, conv, hierarchy, channels, latent, variational, act):
        super().__init__()
        L = len(channels) - 1
        self.convs = nn.ModuleList(build_conv(conv, channels[i], channels[i + 1], hierarchy, i, f"encoder block {i}")
                                   for i in range(L))
        self.pools = nn.ModuleList(_Sparse(hierarchy.down[i]) for i in range(L))
        self.kept = []  # per level: the name of a buffer of the rows the pooling keeps, or None
        for i, c in enumerate(self.convs):
            rows = selected_rows(hierarchy.down[i]) if _fuses(c) else None
            self.kept.append(None if rows is None else f"kept_{i}")
            if rows is not None:  # derived from the hierarchy: not part of a checkpoint
                self.register_buffer(f"kept_{i}", torch.from_numpy(rows), persistent=False)
        self.act = act()
        d = hierarchy.levels[L].n_vertices * channels[-1]
        self.mu = nn.Linear(d, latent)
        self.logvar = nn.Linear(d, latent) if variational else None

    def forward(self, x):
        for conv, pool, kept in zip(self.convs, self.pools, self.kept):
            x = self.act(conv(x, rows=getattr(self, kept))) if kept else pool(self.act(conv(x)))
        h = x.flatten(1)
        return self.mu(h), (self.logvar(h) if self.logvar is not None else None)


class Decoder(nn.Module):
    """A linear map from the latent, then unpooling, conv and activation per level, and an output conv.

    Where the conv plays ``FusedPoolingConv`` a level is act(conv.forward_up(x, U)) = act(conv(U x)),
    the conv's product taken on the coarse vertices before the up-sampling (the same maths)."""

    def __init__(self, conv, hierarchy, channels, latent_in, out_channels, act):
        super().__init__()
        L = len(channels) - 1
        self.n_last, self.c_last = hierarchy.levels[L].n_vertices, channels[-1]
        self.fc = nn.Linear(latent_in, self.n_last * self.c_last)
        self.unpools = nn.ModuleList(_Sparse(hierarchy.up[i]) for i in reversed(range(L)))
        # mirror of the encoder as in the reference implementations: after up-sampling to level i the
        # conv maps c_{i+2} -> c_{i+1} (c_L -> c_L at the coarsest level), then a last conv to the output
        self.convs = nn.ModuleList(build_conv(conv, channels[min(i + 2, L)], channels[i + 1], hierarchy, i,
                                              f"decoder block {i}") for i in reversed(range(L)))
        self.out = build_conv(conv, channels[1], out_channels, hierarchy, 0, "decoder output")
        self.act = act()
        self.fused = [_fuses(c) for c in self.convs]

    def forward(self, z):
        x = self.fc(z).reshape(len(z), self.n_last, self.c_last)
        for unpool, conv, fused in zip(self.unpools, self.convs, self.fused):
            # conv(U x) without forming U x where the conv fuses the up-sampling (FusedPoolingConv)
            x = self.act(conv.forward_up(x, unpool.M) if fused else conv(unpool(x)))
        return batch_major(self.out(x))


def _acts(act, L: int) -> list:
    """The activation of each of L blocks: act() on all but the last (its output is a code or the
    network's output: no activation, as in the thesis 4.4.3 and Zhou et al.'s reference)."""
    return [act() if i < L - 1 else None for i in range(L)]


class ConvEncoder(nn.Module):
    """Fully convolutional encoder (Zhou et al. 2020): strided convs with residual blocks,
    y = sqrt(1 - r) ELU(conv(x)) + sqrt(r) res(x) (no ELU on the last block)."""

    def __init__(self, conv, hierarchy, channels, latent, variational, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        acts = _acts(act, L)
        self.convs = nn.ModuleList(strided_conv(conv, channels[i], channels[i + 1], hierarchy, i, "down",
                                                residual_rate, acts[i]) for i in range(L))
        d = hierarchy.levels[L].n_vertices * channels[-1]
        self.mu = nn.Linear(d, latent)
        self.logvar = nn.Linear(d, latent) if variational else None

    def forward(self, x):
        for conv in self.convs:
            x = conv(x)
        h = x.flatten(1)
        return self.mu(h), (self.logvar(h) if self.logvar is not None else None)


class ConvDecoder(nn.Module):
    """Fully convolutional decoder: a linear map from the code to the last level, then transposed
    convs with residual blocks mirroring the encoder (no ELU on the last block)."""

    def __init__(self, conv, hierarchy, channels, latent_in, out_channels, act, residual_rate):
        super().__init__()
        L = len(channels) - 1
        self.n_last, self.c_last = hierarchy.levels[L].n_vertices, channels[-1]
        self.fc = nn.Linear(latent_in, self.n_last * self.c_last)
        chans = [out_channels, *channels[1:]]
        acts = _acts(act, L)
        self.convs = nn.ModuleList(strided_conv(conv, chans[i + 1], chans[i], hierarchy, i, "up", residual_rate,
                                                acts[L - 1 - i]) for i in reversed(range(L)))

    def forward(self, z):
        x = self.fc(z).reshape(len(z), self.n_last, self.c_last)
        for conv in self.convs:
            x = conv(x)
        return batch_major(x)


class _Net(nn.Module):
    """The encoder and decoder as one module (``enc``, ``dec``: the state_dict's key prefixes)."""

    def __init__(self, enc, dec):
        super().__init__()
        self.enc, self.dec = enc, dec


class AE:
    """Graph autoencoder composed of a conv and a sampler (thesis 3.4 architecture)."""

    name = "ae"
    task_family = RECONSTRUCT
    variational = False

    def __init__(self, conv: Annotated[Spec, Kind("conv")] = "spiral++",
                 sampler: Annotated[Spec, Kind("sampler")] = "quadric",
                 channels: list[int] | None = None, latent: int = 64, activation: str = "elu",
                 representation: Annotated[Spec, Kind("representation")] = "euclidean",
                 kl_weight: float | None = None, train: dict | None = None,
                 fully_convolutional: bool = False, residual_rate: float = 0.5,
                 latent_vertices: int | None = None):
        if latent_vertices is not None and latent_vertices < 1:
            raise RecipeError(f"latent_vertices: at least 1 latent vertex, got {latent_vertices}")
        if activation not in ACTIVATIONS:
            raise RecipeError(f"activation: unknown {activation!r}{did_you_mean(activation, ACTIVATIONS)}")
        if not plays(conv.cls, Conv):
            raise RecipeError(f"conv: {conv.name} does not play the conv role (name, build_args, strided, "
                              "forward, reset_parameters; see fwk.protocols.Conv)")
        self.conv, self.sampler = conv, sampler
        self.channels = list(channels) if channels else [16, 32, 64, 128]
        self.latent, self.activation = latent, activation
        self.representation, self.kl_weight, self.train_overrides = representation, kl_weight, train or {}
        self.rep = self.net = self.hierarchy = None
        self.shape = None
        self.fully_convolutional, self.residual_rate = fully_convolutional or bool(latent_vertices), residual_rate
        self.latent_vertices = latent_vertices
        if latent_vertices:  # z is the flattened (latent_vertices, c_L) map of the last strided convolution
            self.latent = latent_vertices * self.channels[-1]

    @property
    def latent_size(self) -> int:
        """The size of the code z (``latent``, or latent_vertices x c_L)."""
        return self.latent

    # ---- the NetworkFactory role
    def _hierarchy(self, template, ctx=None):
        if self.hierarchy is None:
            h = self.sampler.build().build(template, ctx.cache if ctx is not None else None)
            if self.latent_vertices:
                h = with_latent_level(h, len(self.channels), self.latent_vertices,
                                      radius=int(self.sampler.params.get("radius", 2)))
            self.hierarchy = h
        return self.hierarchy

    def build_encoder(self, template, in_channels: int, ctx=None) -> nn.Module:
        """A module (b, n, in_channels) -> (mu (b, latent_size), logvar (vae) or None (ae))."""
        h = self._hierarchy(template, ctx)
        ch = [in_channels, *self.channels][: len(h.levels)]
        act = ACTIVATIONS[self.activation]
        if self.latent_vertices:
            return LatentConvEncoder(self.conv, h, ch, self.variational, act, self.residual_rate)
        if self.fully_convolutional:
            return ConvEncoder(self.conv, h, ch, self.latent, self.variational, act, self.residual_rate)
        return Encoder(self.conv, h, ch, self.latent, self.variational, act)

    def build_decoder(self, template, out_channels: int, ctx=None, latent_in: int | None = None,
                      latent_parts: list[int] | None = None) -> nn.Module:
        """A module (b, d) -> (b, n, out_channels), d = ``latent_size`` by default.

        ``latent_parts = [d_0, d_1, ...]``: the input is Z = [z_0 | z_1 | ...], codes of networks
        with this one's latent layout (d = sum d_j). With ``latent_vertices`` the first transposed
        convolution reads them as one (b, n_latent, sum_j d_j / n_latent) map, channels
        concatenated per latent vertex, without a dense layer (Deep Spectral Meshes, thesis 4.4.2);
        a flat code (``latent``) is one latent vertex, read through the decoder's own linear
        layer. ``latent_in``: a foreign flat code of d entries, through a linear layer first."""
        if latent_in is not None and latent_parts is not None:
            raise RecipeError("build_decoder: give latent_in (a flat code) or latent_parts (codes of latent maps), "
                              "not both")
        h = self._hierarchy(template, ctx)
        ch = [out_channels, *self.channels][: len(h.levels)]
        act = ACTIVATIONS[self.activation]
        if self.latent_vertices:
            return LatentConvDecoder(self.conv, h, ch, out_channels, act, self.residual_rate, latent_in, latent_parts)
        d = sum(int(x) for x in latent_parts) if latent_parts is not None else (latent_in or self.latent)
        if self.fully_convolutional:
            return ConvDecoder(self.conv, h, ch, d, out_channels, act, self.residual_rate)
        return Decoder(self.conv, h, ch, d, out_channels, act)

    # ---- the model roles
    def fit(self, data, ctx) -> None:
        self.rep, F, Fv = fit_features(self.representation, data)
        self.shape = tuple(F.shape[1:])
        self._template = data.template
        seed_everything(ctx.seed)
        c = self.shape[1]
        self.net = _Net(self.build_encoder(data.template, c, ctx), self.build_decoder(data.template, c, ctx))
        config = ctx.train.replace(**self.train_overrides)
        kl = config.kl_weight if self.kl_weight is None else self.kl_weight
        module = autoencoder_module(self.net, self.rep.unscale, kl)
        fit(module, F, Fv, ctx, self.name, config)
        self.net.eval()

    @torch.no_grad()
    def encode(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, latent_size) the (posterior mean) code."""
        mu, _ = self.net.enc(torch.as_tensor(self.rep.encode(P)))
        return mu.numpy().astype(np.float64)

    @torch.no_grad()
    def decode(self, z, target=None) -> np.ndarray:
        """(b, latent_size) -> (b, n, 3); ``target`` places dr outputs (see ``reconstruct``)."""
        G = self.net.dec(torch.as_tensor(np.asarray(z), dtype=torch.float32))
        return self.rep.decode(G.numpy(), None, target)

    def reconstruct(self, P) -> np.ndarray:
        """Decode the (posterior mean) code; dr outputs are registered to the input (thesis 3.3.10)."""
        return self.decode(self.encode(P), target=P)

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """Decode n codes drawn from N(0, I) (deterministic for a seed)."""
        return self.decode(np.random.default_rng(seed).standard_normal((n, self.latent)))

    def state_dict(self) -> dict:
        return {"net": self.net.state_dict(), "rep": self.rep.state_dict(), "shape": self.shape,
                "template_vertices": self._template.vertices, "template_triangles": self._template.triangles}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a ``state_dict``; ``ctx`` (optional) lends the run's cache to the hierarchy."""
        self.rep = self.representation.build()
        self.rep.load_state_dict(d["rep"], ctx)
        self.shape = tuple(d["shape"])
        self._template = Template(d["template_vertices"], d["template_triangles"])
        c = self.shape[1]
        self.net = _Net(self.build_encoder(self._template, c, ctx), self.build_decoder(self._template, c, ctx))
        self.net.load_state_dict(d["net"])
        self.net.eval()


class VAE(AE):
    """Graph variational autoencoder (reparameterised latent, weighted KL term)."""

    name = "vae"
    variational = True


@hookimpl
def fwk_register_models():
    return [AE, VAE]
