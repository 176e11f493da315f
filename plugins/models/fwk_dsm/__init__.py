"""Model ``dsm``: Deep Spectral Meshes (thesis chapter 4, figure 4.1, sections 4.2, 4.4, 4.5;
Kosk et al., Electronics 13(4):720, 2024).

Bands (eqs. 4.2, 4.11). The ``spectral`` assembler is fitted on the mean training shape P-bar
(cotangent Laplacian L, Voronoi mass matrix M, U the first k generalised eigenvectors,
X = U_k U_k^T M, never formed). Each training mesh P is split into

    P_low = X (P - P-bar) + P-bar          P_high = (I - X)(P - P-bar) + P-bar

(``k`` a list of cut points gives more bands; the last band is always "everything above the
last cut"). Every band is a mesh centred on the mean, so each gets its own representation
g_b, fitted on that band of the training set: thesis default ``euclidean`` std for the low
band(s) and ``dr`` norm with the training mean as reference for the high band.

The assembler is the recipe's ``assembler`` (default ``spectral``), built with dsm's ``k`` and
``mass``; the representations are ``low_representation`` (every band below the last cut) and
``high_representation`` (the band above it), or one per band in ``representations``.

Network (4.2.2, 4.4.2-4.4.3). One encoder E_b and one decoder D_b per band, built by ``network``
(or ``networks``, one per band): any model playing ``fwk.protocols.NetworkFactory`` (``vae``: the
thesis uses the fully convolutional vcconv VAE, channels [|f|, 32, 64, 128, 128, 4], with 8
latent vertices x 4 channels = 32 entries per band). Encoders give (mu_b, log sigma_b^2);
mu = [mu_0 | ... | mu_B], sigma likewise, Z = mu + sigma * eps, and every decoder reads the
whole Z: D_b decodes its band from Z_b conditioned on the other bands' codes.

How a decoder reads Z (figure 4.1, 4.4.2: "Z in R^{8 x 8}"): each band's code is a latent map,
Z_b in R^{n_latent x c_b} (flattened vertex-major), and D_b's first transposed convolution reads
the (n_latent, c_0 + ... + c_B) map whose row v holds every band's channels at latent vertex v
(``build_decoder(..., latent_parts=[|Z_0|, ..., |Z_B|])``), so there is no dense layer between Z
and the decoders: an entry of latent vertex v reaches, in the first layer, only the vertices in
v's support. Networks with a flat code (no ``latent_vertices``: one latent vertex) read the
concatenated Z through their own first linear layer, as their decoders read their own code.
With ``networks:`` the bands' networks must share the latent level (sampler and
``latent_vertices``) for the rows of the map to be the same latent vertices.

Conditioning Factor gamma (4.5). During training the other bands' entries seen by D_b are
zeroed with probability 1 - gamma. Semantics chosen here (``conditioning_dropout: band``):
one Bernoulli(gamma) draw per training sample, per decoder and per other band, masking that
band's whole code, with no 1/gamma rescaling. Why: zero is the prior mean, so a masked band
reads as "the average face's band", an input that also occurs at inference (``sample`` draws
around it); a whole-band mask makes D_b reconstruct from Z_b alone on a 1 - gamma share of the
samples, which is what decouples the bands (an element mask leaves most of the conditioning
visible on every sample); without rescaling the unmasked inputs have exactly the inference
distribution, and gamma = 0 (always masked: no conditioning, the thesis's extreme case) stays
defined. ``conditioning_dropout: element`` masks each entry independently instead (closer to a
literal nn.Dropout, still without rescaling). Nothing is masked at inference.

Training (4.4.4, eqs. 4.13-4.14). One Adam per band (Lightning manual optimisation), each
updating only E_b and D_b with

    L_b = || unscale_b(F_b) - unscale_b(D_b(Z)) ||_1 + phi KL(N(0, I) || q(Z_b | F_b))

(unscale = denorm for norm, destd for std: the L1 in each representation's own unscaled space;
phi = ``kl_weight``, default the recipe's ``train.kl_weight``, thesis 1e-6), per-epoch
exponential learning-rate decay (``train.lr_decay``). The other bands' codes enter D_b
detached, so L_b reaches no other band's encoder: exactly "E_b, D_b are optimised in terms of
L_b". Thesis settings: lr 1e-4, decay 0.99, batch 16, 500 epochs.

Inference (4.4.5, eq. 4.15). Encode every band (posterior means), decode every band from Z,
convert back to positions (dr: integrated and placed onto its reference, the mean; never onto
the ground truth) and assemble

    P' = X (P'_low - P-bar) + (I - X)(P'_high - P-bar) + P-bar

so each band contributes only its own frequencies. With perfect decoders (ground-truth
features) the assembly returns the input exactly (tested to 1e-8).

API (roles ``ReconstructionModel`` and ``BandModel`` of ``fwk.protocols``): ``encode(P) -> Z``
(b, |Z|), ``decode(Z) -> P'``, ``decode_bands(Z)``, ``reconstruct(P)``, ``sample(n, seed)``
(Z ~ N(0, I)), ``latent_size`` (|Z|), ``band_names``, ``latent_slice(name)`` / ``slices`` (the
entries of Z of one band), ``split(P)``, ``assemble(bands)``, ``band_shares(D)``; also
``features(P)``. Training: ``fwk_dsm.module.DSMModule``.
"""
from __future__ import annotations

from typing import Annotated

import numpy as np
import torch
from torch import nn

from fwk.data import Template
from fwk.engine import fit, kl_divergence, l1_mean, seed_everything
from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT, NetworkFactory
from fwk.recipes import Kind, Spec

DROPOUT_MODES = ("band", "element")


def conditioning_mask(batch: int, n_bands: int, gamma: float, mode: str = "band", latents=None,
                      generator: torch.Generator | None = None, device=None) -> list[list[torch.Tensor]]:
    """Masks for the decoders' views of Z during training: ``masks[b][j]`` multiplies band j's
    code in decoder b's input; ones for j == b, Bernoulli(gamma) otherwise (shape (batch, 1)
    for ``band``, (batch, latents[j]) for ``element``)."""
    out = []
    for b in range(n_bands):
        row = []
        for j in range(n_bands):
            width = 1 if mode == "band" else int(latents[j])
            if j == b:
                row.append(torch.ones(batch, width, device=device))
            else:
                row.append((torch.rand(batch, width, generator=generator, device=device) < gamma).float())
        out.append(row)
    return out


class DSMNet(nn.Module):
    """Encoders and decoders of every band; ``forward`` returns (outputs, mus, logvars)."""

    def __init__(self, encoders, decoders, latents, gamma: float, mode: str = "band"):
        super().__init__()
        self.encoders = nn.ModuleList(encoders)
        self.decoders = nn.ModuleList(decoders)
        self.latents = [int(x) for x in latents]
        self.gamma, self.mode = float(gamma), mode
        self.last_masks = None  # the masks of the last forward pass (tests, diagnostics)

    @property
    def n_bands(self) -> int:
        return len(self.encoders)

    def encode(self, feats):
        mus, logvars = [], []
        for enc, F in zip(self.encoders, feats):
            mu, logvar = enc(F)
            mus.append(mu)
            logvars.append(logvar)
        return mus, logvars

    def decoder_inputs(self, zs, detach_others: bool = True):
        """Decoder b's view of Z: its own code, the others masked (training only) and detached."""
        B = self.n_bands
        masks = None
        if self.training and self.gamma < 1.0:
            masks = conditioning_mask(len(zs[0]), B, self.gamma, self.mode, self.latents, device=zs[0].device)
        self.last_masks = masks
        ins = []
        for b in range(B):
            parts = []
            for j, z in enumerate(zs):
                x = z if (j == b or not detach_others) else z.detach()
                if masks is not None and j != b:
                    x = x * masks[b][j]
                parts.append(x)
            ins.append(torch.cat(parts, dim=1))
        return ins

    def decode(self, zs, detach_others: bool = True):
        return [dec(x) for dec, x in zip(self.decoders, self.decoder_inputs(zs, detach_others))]

    def forward(self, feats, sample: bool | None = None):
        sample = self.training if sample is None else sample
        mus, logvars = self.encode(feats)
        zs = [mu + torch.randn_like(mu) * torch.exp(0.5 * lv) if (sample and lv is not None) else mu
              for mu, lv in zip(mus, logvars)]
        return self.decode(zs), mus, logvars


def band_losses(net: DSMNet, feats, unscales, kl_weight: float):
    """Per-band losses L_b (eqs. 4.13-4.14) and their L1 terms."""
    outs, mus, logvars = net(feats)
    losses, l1s = [], []
    for G, F, un, mu, lv in zip(outs, feats, unscales, mus, logvars):
        l1 = l1_mean(un(G), un(F))
        l1s.append(l1)
        losses.append(l1 + kl_weight * kl_divergence(mu, lv))
    return losses, l1s


class DSM:
    """Deep Spectral Meshes: one VAE per spectral band, shared latent, Conditioning Factor gamma.

    Nested components are recipe parameters (``fwk.recipes.Spec``): ``network`` / ``networks``
    (models playing ``NetworkFactory``), ``representations`` or ``low_representation`` /
    ``high_representation``, and ``assembler`` (built with ``k`` and ``mass``).
    """

    name = "dsm"
    task_family = RECONSTRUCT

    def __init__(self, network: Annotated[Spec, Kind("model", NetworkFactory)] = "vae",
                 networks: Annotated[list[Spec], Kind("model")] | None = None,
                 k: int | list[int] = 500, mass: bool = True,
                 representations: Annotated[list[Spec], Kind("representation")] | None = None,
                 band_names: list[str] | None = None, gamma: float = 1.0, conditioning_dropout: str = "band",
                 kl_weight: float | None = None, train: dict | None = None,
                 low_representation: Annotated[Spec, Kind("representation")] = "euclidean",
                 high_representation: Annotated[Spec, Kind("representation")] = "dr",
                 assembler: Annotated[Spec, Kind("assembler")] = "spectral"):
        if not 0.0 <= float(gamma) <= 1.0:
            raise RecipeError(f"gamma: the Conditioning Factor lies in [0, 1], got {gamma}")
        if conditioning_dropout not in DROPOUT_MODES:
            raise RecipeError(f"conditioning_dropout: expected one of {', '.join(DROPOUT_MODES)}, got {conditioning_dropout!r}")
        cuts = [k] if isinstance(k, int) else list(k)
        if not cuts or any(int(c) != c or c <= 0 for c in cuts) or cuts != sorted(set(cuts)):
            raise RecipeError(f"k: cut points must be positive increasing integers, got {k}")
        self.cuts_param = [int(c) for c in cuts]
        self.cuts = list(self.cuts_param)
        n_bands = len(cuts) + 1
        if networks is not None and len(networks) != n_bands:
            raise RecipeError(f"networks: {len(networks)} given for {n_bands} bands (k = {k})")
        if representations is not None and len(representations) != n_bands:
            raise RecipeError(f"representations: {len(representations)} given for {n_bands} bands (k = {k})")
        if band_names is not None and (len(band_names) != n_bands or len(set(band_names)) != n_bands):
            raise RecipeError(f"band_names: give {n_bands} distinct names (k = {k})")
        self.network, self.networks = network, networks
        self.mass, self.gamma, self.conditioning_dropout = bool(mass), float(gamma), conditioning_dropout
        # thesis defaults: euclidean std below the last cut, dr norm (against the mean) above it
        self.rep_specs = list(representations) if representations is not None else (
            [low_representation] * (n_bands - 1) + [high_representation])
        self.assembler_spec = assembler
        self._band_names = list(band_names) if band_names else (
            ["low", "high"] if n_bands == 2 else [*(f"band{i}" for i in range(n_bands - 1)), "high"])
        self.kl_weight, self.train_overrides = kl_weight, dict(train or {})
        self.reps = self.assembler = self.net = self.template = None
        self._net_models = None
        self.channels = self.latents = None

    # ------------------------------------------------------------------ parts
    @property
    def n_bands(self) -> int:
        return len(self.cuts_param) + 1

    @property
    def band_names(self) -> list[str]:
        """The bands' names, low to high (``low``/``high``, or ``band0``, ... ``high``)."""
        return self._band_names

    def _net_model(self, b: int):
        if self._net_models is None:
            specs = self.networks or [self.network] * self.n_bands
            models, cache = [], {}
            for i, s in enumerate(specs):
                key = id(s)
                if key not in cache:  # one instance per distinct spec: its hierarchy is built once
                    m = s.build()
                    if not isinstance(m, NetworkFactory):
                        where = f"networks[{i}]" if self.networks else "network"
                        raise RecipeError(f"{where}: model {s.name!r} lends no networks (it does not play "
                                          "fwk.protocols.NetworkFactory: build_encoder, build_decoder, "
                                          "latent_size, variational)")
                    cache[key] = m
                models.append(cache[key])
            self._net_models = models
        return self._net_models[b]

    def _make_reps(self):
        return [s.build() for s in self.rep_specs]

    def _make_assembler(self, cuts):
        return self.assembler_spec.build(k=cuts if len(cuts) > 1 else cuts[0], mass=self.mass)

    def _fit_assembler(self, template, mean, cache=None, log=None):
        n = template.n_vertices
        cuts = sorted({min(c, n) for c in self.cuts_param})
        if cuts != self.cuts_param and log is not None:
            log(f"[dsm] k = {self.cuts_param} exceeds the template's {n} vertices: cut points clamped to {cuts}"
                + (" (the last band is then empty)" if cuts[-1] == n else ""))
        if len(cuts) != len(self.cuts_param):
            raise RecipeError(f"k: cut points {self.cuts_param} collapse on a template of {n} vertices; "
                              f"give cut points below {n}")
        self.cuts = cuts
        a = self._make_assembler(cuts)
        a.fit(template, mean, cache=cache)
        self.assembler = a

    def _make_net(self, template, ctx=None) -> DSMNet:
        encs, decs, latents = [], [], []
        for b in range(self.n_bands):
            m = self._net_model(b)
            latents.append(int(m.latent_size))
        for b, c in enumerate(self.channels):
            m = self._net_model(b)
            encs.append(m.build_encoder(template, c, ctx))
            # Z = [Z_0 | ... | Z_B] read as one latent map (thesis 4.4.2, fig. 4.1): no dense front end
            decs.append(m.build_decoder(template, c, ctx, latent_parts=latents))
        self.latents = latents
        return DSMNet(encs, decs, latents, self.gamma, self.conditioning_dropout)

    @property
    def slices(self) -> dict[str, slice]:
        """Band name -> its entries of Z."""
        out, start = {}, 0
        for name, d in zip(self.band_names, self.latents):
            out[name] = slice(start, start + d)
            start += d
        return out

    def latent_slice(self, band: str | int) -> slice:
        """The entries of Z that band ``band`` (its name or index) owns."""
        if isinstance(band, int):
            band = self.band_names[band]
        if band not in self.slices:
            raise DataError(f"band {band!r}: unknown; the model's bands are {', '.join(self.band_names)}")
        return self.slices[band]

    @property
    def latent_size(self) -> int:
        """|Z|: the sum of the bands' latent sizes (each band network's ``latent_size``)."""
        if self.latents is None:
            return int(sum(self._net_model(b).latent_size for b in range(self.n_bands)))
        return int(sum(self.latents))

    # ------------------------------------------------------------------ data
    def split(self, P) -> list[np.ndarray]:
        """The bands of meshes P (b, n, 3) (the assembler's split, eq. 4.11), each centred on the mean."""
        return self.assembler.split(np.asarray(P, dtype=np.float64))

    def features(self, P) -> list[np.ndarray]:
        """Per-band scaled features F_b of meshes P (b, n, 3)."""
        return [rep.encode(band) for rep, band in zip(self.reps, self.split(P))]

    def assemble(self, bands) -> np.ndarray:
        """Eq. 4.15 for per-band position predictions."""
        return self.assembler.assemble(bands)

    def band_shares(self, D) -> np.ndarray:
        """(..., n, 3) displacements -> (..., bands): the share of their energy in each band
        (the assembler's ``band_shares``; they sum to 1)."""
        return self.assembler.band_shares(D)

    def decode_features(self, feats) -> np.ndarray:
        """Per-band features -> positions -> assembled mesh (no ground truth involved)."""
        return self.assemble([rep.decode(np.asarray(F)) for rep, F in zip(self.reps, feats)])

    # ------------------------------------------------------------------ fitting
    def fit(self, data, ctx) -> None:
        """Fit the assembler and the bands' representations on the training shapes, then train
        the bands' networks (``DSMModule``)."""
        from .module import DSMModule  # deferred: Lightning's import (2-5 s, see .module) only when training

        P, V = data.stack("train"), data.stack("val")
        self.template = data.template
        mean = P.mean(axis=0)
        self._fit_assembler(data.template, mean, ctx.cache, ctx.log)
        self.reps = self._make_reps()
        bands = self.split(P)
        for rep, band in zip(self.reps, bands):
            rep.fit(band, mean, data.template)
        F = [torch.as_tensor(rep.encode(band)) for rep, band in zip(self.reps, bands)]
        Fv = None
        if len(V):
            Fv = tuple(torch.as_tensor(rep.encode(band)) for rep, band in zip(self.reps, self.split(V)))
        self.channels = [int(f.shape[-1]) for f in F]
        seed_everything(ctx.seed)
        self.net = self._make_net(data.template, ctx)
        config = ctx.train.replace(**self.train_overrides)
        kl = config.kl_weight if self.kl_weight is None else self.kl_weight
        ctx.log(f"[dsm] {self.n_bands} bands {self.band_names} at k = {self.cuts}, "
                f"representations {[r.name for r in self.reps]}, |Z| = {self.latents}, "
                f"gamma = {self.gamma}")
        fit(DSMModule(self.net, [r.unscale for r in self.reps], kl, self.band_names), tuple(F), Fv, ctx,
            self.name, config)
        self.net.eval()

    # ------------------------------------------------------------------ inference
    def _check(self):
        if self.net is None:
            raise RuntimeError("dsm: not fitted")

    @torch.no_grad()
    def encode(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, |Z|) posterior means [mu_0 | ... | mu_B]."""
        self._check()
        self.net.eval()
        P = np.asarray(P, dtype=np.float64)
        mus, _ = self.net.encode([torch.as_tensor(f) for f in self.features(P)])
        return torch.cat(mus, dim=1).numpy().astype(np.float64)

    @torch.no_grad()
    def decode_band_features(self, z) -> list[np.ndarray]:
        self._check()
        self.net.eval()
        Z = torch.as_tensor(np.atleast_2d(np.asarray(z)), dtype=torch.float32)
        zs = [Z[:, s] for s in self.slices.values()]
        return [G.numpy() for G in self.net.decode(zs)]

    def decode_bands(self, z) -> list[np.ndarray]:
        """Z -> per-band positions P'_b (each centred on the mean, before assembly)."""
        return [rep.decode(G) for rep, G in zip(self.reps, self.decode_band_features(z))]

    def decode(self, z, target=None) -> np.ndarray:
        """Z (b, |Z|) -> assembled meshes (b, n, 3) (eq. 4.15). ``target`` is ignored: dsm needs
        and allows no registration to the ground truth."""
        return self.assemble(self.decode_bands(z))

    def reconstruct(self, P) -> np.ndarray:
        """Encode (posterior means) and decode: eq. 4.15, never registered to the input."""
        return self.decode(self.encode(P))

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n meshes decoded from Z ~ N(0, I) (deterministic for a seed)."""
        return self.decode(np.random.default_rng(seed).standard_normal((n, self.latent_size)))

    # ------------------------------------------------------------------ saving
    def state_dict(self) -> dict:
        self._check()
        return {"kind": self.name, "net": self.net.state_dict(), "reps": [r.state_dict() for r in self.reps],
                "assembler": self.assembler.state_dict(), "cuts": list(self.cuts), "channels": list(self.channels),
                "band_names": list(self.band_names), "gamma": self.gamma,
                "template_vertices": self.template.vertices, "template_triangles": self.template.triangles}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a fitted model; ``ctx`` (optional) lends the run's cache to the networks' hierarchies."""
        self.template = Template(np.asarray(d["template_vertices"]), np.asarray(d["template_triangles"]))
        self.cuts, self.channels = [int(c) for c in d["cuts"]], [int(c) for c in d["channels"]]
        self._band_names = list(d["band_names"])
        self.reps = self._make_reps()
        for r, s in zip(self.reps, d["reps"]):
            r.load_state_dict(s, ctx=ctx)
        self.assembler = self._make_assembler(self.cuts)
        self.assembler.load_state_dict(d["assembler"], ctx=ctx)
        self.net = self._make_net(self.template, ctx)
        self.net.load_state_dict(d["net"])
        self.net.eval()


@hookimpl
def fwk_register_models():
    return [DSM]
