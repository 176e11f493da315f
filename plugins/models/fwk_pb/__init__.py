"""Models ``pb`` and ``pbs``: personalised blendshapes from a neutral head (thesis chapter 5).

Data (thesis 5.2.1; the task preprocesses): each neutral is centred, rigidly registered to the
mean training neutral P-bar and the whole dataset scaled into [-1, 1]; a subject's expressions
move with its neutral. Inputs and targets (eqs. 5.1-5.4):

    F_neut = g(P_neutral - P-bar)            F_expr = g(P_expression - P_neutral)

where g is a representation: ``euclidean`` (std: per-vertex standardisation of the offsets) or
``dr`` (norm: the deformation of the neutral from P-bar, and of the expression from the
subject's own neutral, normalised into [-1, 1]).

g of expression n is scaled with the statistics of that expression's training subjects, as the
thesis's network for expression n sees them (its means P-bar_expression n, 5.2.1): a network's
zero output is its expression's mean offset. fwk fits the representation once on every
expression's offsets (one operator set for ``dr``) and then re-scales each expression's
features with a scaler of the representation's settings (``fwk.scaling.Scaler.like``) fitted
on that expression alone: both maps are affine and increasing, so the features are those of a
representation fitted on the expression alone (tested), for std and norm alike. This matters
most for a conditional model (below): with one scaling for all expressions, its zero output is
the mean offset over all of them, and an expression whose offset is small against the others'
(a blink against a jaw opening) contributes so little to the loss that the network learned to
leave it out (measured on the 57-expression ICT rig: gains of 0.001-0.01 for eyeBlink_L and
browInnerUp_L, on training subjects too). A model saved before this scaling loads as it was
trained (one scaling).

``pb`` (section 5.2), ``mode: end-to-end``: per expression one variational graph autoencoder
E_neutral -> z -> D_expression, loss (eqs. 5.5 / 5.6)

    L = || unscale(F_expr) - unscale(D(z)) ||_1 + phi KL(N(0, 1) || q(z | F_neut))

(unscale = denorm for norm, destd for std: the L1 norm in the representation's own units),
inference (eq. 5.7) P'_expr = g^-1(D(mu)) + P_neutral (for ``dr``: integrated against the
neutral). ``mode: two-step`` (5.2.2): step 1 trains a VAE on neutrals alone (all training
neutrals, with or without expressions); its encoder is frozen; step 2 trains one decoder per
expression from the neutral's latent mean. The networks come from any registered model
playing ``fwk.protocols.NetworkFactory`` (``network: {name: vae, ...}``): its ``build_encoder``
/ ``build_decoder``.

``pbs`` (section 5.3): two end-to-end PB networks trained together (one loop, one optimiser,
separate parameters and losses), one ``euclidean`` std (spatial) and one ``dr`` norm
(differential). At inference both are converted to positions and assembled (eq. 5.10)

    P'_expr = (I - X_k) P'_diff + X_k P'_spatial,      X_k = U_k U_k^T M

with the ``assembler`` (default ``spectral``) fitted on the mean neutral (U_k: the k smallest
generalised eigenvectors of its cotangent Laplacian, M its mass matrix; X_k never formed).
k = 0 gives P'_diff, k = n gives P'_spatial. The differential prediction carries no position;
PBS places it by a rigid (Kabsch) fit onto P'_spatial, so no ground truth is needed at
inference.

Pareto-optimal k (5.3.4): after training, for every expression the validation subjects are
assembled at every k of a sweep (default: the thesis's grid as printed, {0, 10, ..., 100, 120,
..., 200, 230, ..., 500, 550, ..., 1000, n}, values >= n clamped to the template's n and
deduplicated: 37 values on ICT-FaceKit's 11,248 vertices as on the thesis's 14,921) and scored with the ``sweep_metrics`` (L1 and the perceptual DAME and FMPD); the
Pareto front of (``distance_metric``, ``knee_metric``), the thesis's (L1, FMPD), is found and k
is chosen at its knee: both objectives are normalised to [0, 1] over the front, and the knee is
the front point farthest below the chord joining the front's two ends (the "maximum distance
to the chord" rule); a front of two points has no bend, so it takes the point with the
smallest x / min x + y / min y (relative excess). The sweep, the fronts and the choice are kept
in the state and saved with the run; ``predict`` and ``fwk apply`` use the chosen k
(``fwk.protocols.CutSelectingModel``); ``parts`` gives the two networks alone
(``fwk.protocols.CompositeModel``).

Beyond the thesis (its future work, ``conditional: true``): one network pair for all
expressions, the expression given to the decoders as a one-hot condition concatenated to z
(a foreign flat code: ``build_decoder(..., latent_in=)`` reads it through a linear layer, also
when the network's own code is a latent map). It trains on (subject, expression) pairs: a batch
is ``batch_size`` pairs, each decoded with its own expression's one-hot, the loss per network the
mean L1 over the pairs plus phi KL.

Beyond the thesis (issue 31; what the band swaps of ``benchmarks/pbs_band_errors.py`` point to):

``anchor: {name: dt, sources: [0, 1, 2]}`` (any model playing ``fwk.protocols.BlendshapeModel``):
the anchor is fitted on the training split first and every expression's features are taken
against its prediction A_expr = anchor(P_neutral) instead of the neutral (eqs. 5.3 / 5.4 with
the reference changed)

    F_expr = g(P_expression - A_expr)            P'_expr = g^-1(D(mu)) + A_expr

(for ``dr``: the deformation from A_expr to the expression, integrated against A_expr), so each
network learns the residual of the anchor's transfer, and a zero residual (the representation's
features of "no change") gives the anchor's output exactly, at every k of the assembly (tested
against DT). The networks' input is still the neutral. With Deformation Transfer as the anchor
this is Li, Weise and Pauly 2010 ("Example-based facial rigging") in spirit: start from DT, which
carries the source's smooth, plausible deformation, and correct it from examples; the networks'
errors then scale with the residual, not with the whole expression. The anchor's state is saved
with the model; at inference its predictions are computed once per set of neutrals for every
expression (DT: one factorisation per neutral) and shared by both networks and the k sweep.

``bending_weight: w`` (default 0): the spatial network's loss (branch 0) gains

    w * mean_{b, i, c} | (L (unscale(D(z)) - unscale(F_expr)))_{b, i, c} |

with L the template's cotangent Laplacian (no mass matrix: cotangent weights are dimensionless,
so for euclidean offsets the term is in the offsets' own units and w = 1 weighs bending as much
as position). For euclidean offsets L applied to the error is the error of the (area-weighted)
mean-curvature normals: the bending error below k that the band swaps measured costs PBS its
DAME. For another representation it is the roughness of the feature error.
"""
from __future__ import annotations

import hashlib
from types import MappingProxyType
from typing import Annotated

import numpy as np
import torch
from torch import nn

from fwk.data import Template
from fwk import engine
from fwk.engine import autoencoder_module, kl_divergence, l1_mean, loss_module, reparameterize
from fwk.errors import DataError, RecipeError
from fwk.evaluation import evaluate, pareto_front
from fwk.hookspecs import hookimpl
from fwk.geometry.operators import cotangent_laplacian
from fwk.protocols import BLENDSHAPES, BlendshapeModel, NetworkFactory, Packable, TruncatesCuts
from fwk.recipes import Kind, Spec, make_spec
from fwk.scaling import Scaler

# thesis 5.3.4: K = {0, 10, ..., 100, 120, ..., 200, 230, ..., 470, 500, 550, ..., 1000, 14921}, |K| = 37
THESIS_KS = [*range(0, 101, 10), *range(120, 201, 20), *range(230, 471, 30), *range(500, 1001, 50)]
MODES = ("end-to-end", "two-step")


def thesis_ks(n: int) -> list[int]:
    """The thesis's k grid (5.3.4) as printed, for a template of n vertices: {0, 10, ..., 100,
    120, ..., 200, 230, ..., 470, 500, 550, ..., 1000} and n itself (the thesis's 14,921), values
    >= n clamped to n, deduplicated: 37 values wherever n > 1000. k counts eigenvectors, not a
    share of the vertices, so the values are not rescaled by n / 14,921."""
    return sorted({min(int(k), n) for k in THESIS_KS} | {int(n)})


def knee(x, y) -> int:
    """Index (into x, y) of the knee of a Pareto front given by points (x, y), both minimised:
    normalise both to [0, 1], take the point farthest below the chord joining the two ends."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) <= 2:  # no curve to bend: the smallest relative excess over the best of each objective
        return int(np.argmin(x / max(x.min(), 1e-300) + y / max(y.min(), 1e-300)))
    order = np.argsort(x)
    xs, ys = x[order], y[order]
    xn = (xs - xs[0]) / ((xs[-1] - xs[0]) or 1.0)
    yn = (ys - ys.min()) / (np.ptp(ys) or 1.0)
    a, b = np.array([xn[0], yn[0]]), np.array([xn[-1], yn[-1]])
    d = b - a
    # signed distance below the chord (positive: the front bulges towards the origin)
    dist = (d[0] * (yn - a[1]) - d[1] * (xn - a[0])) / (np.hypot(*d) or 1.0)
    return int(order[int(np.argmin(dist))])


def _build_rep(spec: Spec):
    """A representation from its spec, taken against the reference (``relative: true``) where
    its class offers the choice (``relative_option``) and the recipe does not say."""
    extra = {"relative": True} if spec.cls.relative_option and "relative" not in spec.params else {}
    return spec.build(**extra)


class _Net(nn.Module):
    def __init__(self, enc, dec):
        super().__init__()
        self.enc, self.dec = enc, dec


def _joint_module(owner, kl_weight: float, stage_name: str):
    """One LightningModule training every network of ``owner`` together (sum of the losses;
    separate parameters, so each net gets exactly its own loss's gradient)."""

    def loss(module, batch, stage):
        B, E = owner.n_branches, len(owner.expressions)
        X, Y, mask = batch[:B], batch[B:B + B * E], batch[-1]
        total = 0.0
        for b in range(B):
            z = owner._latent(b, X[b], sample=module.training)
            kl = z[1]
            for e in range(E):
                m = mask[:, e]
                if not bool(m.any()):
                    continue
                G = owner._decode(b, e, z[0])
                Gu, Yu = owner.unscale(b, e, G[m]), owner.unscale(b, e, Y[b * E + e][m])
                err = l1_mean(Gu, Yu)  # mean |Gu - Yu|, one pass each way (fwk.native.ops)
                total = total + err
                if b == 0 and owner.bending_weight:
                    bend = owner.bending_error(Gu - Yu)
                    total = total + owner.bending_weight * bend
                    module.log(f"{stage}_bending_{owner.expressions[e]}", bend, on_epoch=True, on_step=False,
                               batch_size=int(m.sum()))
                module.log(f"{stage}_l1_{owner.branch_names[b]}_{owner.expressions[e]}", err, on_epoch=True,
                           on_step=False, batch_size=int(m.sum()))
            total = total + kl_weight * kl
        module.log(f"{stage}_loss", total, prog_bar=True, on_epoch=True, on_step=False, batch_size=len(mask))
        return total

    return loss_module({"nets": owner.nets}, loss)


def _conditional_module(owner, kl_weight: float, stage_name: str):
    """A conditional model's training on (subject, expression) pairs: each sample of a batch is
    one pair, encoded from its neutral and decoded with its own expression's one-hot condition;
    per network the loss is the mean L1 over the batch's pairs plus phi KL, as one per-expression
    network's (eqs. 5.5 / 5.6)."""

    def loss(module, batch, stage):
        B = owner.n_branches
        X, Y, e = batch[:B], batch[B:2 * B], batch[-1]
        total = 0.0
        for b in range(B):
            zs, kl = owner._latent(b, X[b], sample=module.training, only=0)
            Gu, Yu = owner.unscale(b, e, owner._decode(b, e, zs[0])), owner.unscale(b, e, Y[b])
            err = l1_mean(Gu, Yu)
            module.log(f"{stage}_l1_{owner.branch_names[b]}", err, on_epoch=True, on_step=False, batch_size=len(e))
            total = total + err + kl_weight * kl
            if b == 0 and owner.bending_weight:
                total = total + owner.bending_weight * owner.bending_error(Gu - Yu)
        module.log(f"{stage}_loss", total, prog_bar=True, on_epoch=True, on_step=False, batch_size=len(e))
        return total

    return loss_module({"nets": owner.nets}, loss)


def _pairs(X: list, Y: list, mask: torch.Tensor) -> tuple:
    """Per-subject tensors (inputs X[b] (S, n, c), targets Y[b * E + e] (S, n, c), mask (S, E))
    -> one sample per present (subject, expression) pair: (*X[b][s], *Y[b][s, e], e), subject-major."""
    s, e = torch.nonzero(mask, as_tuple=True)
    B, E = len(X), mask.shape[1]
    Xp = [x[s] for x in X]
    Yp = [torch.stack([Y[b * E + j][i] for i, j in zip(s.tolist(), e.tolist())]) for b in range(B)]
    return (*Xp, *Yp, e)


class _Blend:
    """Shared machinery: branches (one representation each), networks per branch and expression."""

    task_family = BLENDSHAPES
    expressions: list[str] | None = None  # the blendshape role's member, declared on the class; set per instance

    def _init(self, network, branches, mode, expressions, conditional, kl_weight, train, anchor=None,
              bending_weight=0.0):
        if mode not in MODES:
            raise RecipeError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if conditional and mode != "end-to-end":
            raise RecipeError("conditional: only with mode end-to-end")
        self.network = make_spec("model", network, "network")
        self.branch_specs = [make_spec("representation", s, "representation") for s in branches]
        self.mode, self.conditional = mode, conditional
        self.expressions = list(expressions) if expressions else None
        self.kl_weight, self.train_overrides = kl_weight, dict(train or {})
        self.in_reps = self.out_reps = None
        self.expr_scalers = None  # per branch, per expression: fwk.scaling.Scaler (see the module docstring)
        self._expr_stacks = {}  # (branch, dtype, device) -> the expression scalers' (div, shift) stacked
        self.nets = None
        self._net_model = None
        self.template = None
        self.shape = None
        # a recipe's anchor is checked against the role when validated (Kind); one built in Python here
        self.anchor_spec = None if anchor is None else make_spec("model", anchor, "anchor", role=BlendshapeModel)
        if not (np.isfinite(bending_weight) and bending_weight >= 0):
            raise RecipeError(f"bending_weight: expected a finite number >= 0, got {bending_weight!r}")
        self.bending_weight = float(bending_weight)
        self.anchor = None       # the fitted anchor model (a BlendshapeModel), when anchor_spec is set
        self._anchor_memo = {}   # one entry: (neutrals' hash) -> {expression: anchor prediction}
        self._bending = None     # (torch sparse cotangent Laplacian of the template, its dtype)

    def _describe_extras(self) -> str:
        """The options beyond the thesis, for ``describe``."""
        out = []
        if self.anchor_spec is not None:
            p = ", ".join(f"{k}: {v}" for k, v in self.anchor_spec.params.items())
            out.append(f"beyond the thesis: the networks learn the residual from {self.anchor_spec.name}"
                       f"{f' ({p})' if p else ''}'s prediction (a zero residual is {self.anchor_spec.name} itself)")
        if self.bending_weight:
            out.append("beyond the thesis: the spatial network's loss has a bending term of weight "
                       f"{self.bending_weight:g}")
        return "".join(f"; {x}" for x in out)

    # ------------------------------------------------------------------ anchor and bending
    def refs(self, N, expressions) -> dict:
        """{expression: (b, n, 3) the reference each expression's features are taken against}: the
        neutrals themselves (thesis eqs. 5.3 / 5.4), or with an ``anchor`` its prediction for them
        (the anchor's ``predict_all``: one DT factorisation per neutral for every expression).
        The last neutrals' anchor predictions are kept (PBS's two networks and a k sweep ask for
        the same neutrals again)."""
        if self.anchor is None:
            return {e: N for e in expressions}
        key = (N.shape, hashlib.blake2b(np.ascontiguousarray(N).tobytes(), digest_size=16).digest())
        memo = self._anchor_memo.get(key)
        if memo is None or any(e not in memo for e in expressions):
            wanted = list(dict.fromkeys([*expressions, *(self.expressions or [])]))
            memo = {e: np.asarray(v, dtype=np.float64) for e, v in self.anchor.predict_all(N, wanted).items()}
            self._anchor_memo.clear()  # in place: the part models (``single``) share it
            self._anchor_memo[key] = memo
        return {e: memo[e] for e in expressions}

    def bending_error(self, D):
        """Mean |L D| of a (B, n, c) feature error D, L the cotangent Laplacian (no mass matrix)
        of the template: for euclidean offsets the error of the discrete mean-curvature normals
        integrated over each vertex's area, in the offsets' own units (cotangent weights are
        dimensionless), so a weight of 1 weighs bending as much as position."""
        if self._bending is None or self._bending.dtype != D.dtype:
            L = cotangent_laplacian(self.template.vertices, self.template.triangles).tocoo()
            idx = torch.as_tensor(np.stack([L.row, L.col]), dtype=torch.long)
            self._bending = torch.sparse_coo_tensor(idx, torch.as_tensor(L.data, dtype=D.dtype), L.shape,
                                                    check_invariants=True).coalesce()
        B, n, c = D.shape
        LD = torch.sparse.mm(self._bending, D.permute(1, 0, 2).reshape(n, B * c))
        return LD.abs().mean()

    # ------------------------------------------------------------------ networks
    @property
    def n_branches(self) -> int:
        return len(self.branch_specs)

    def _network_model(self):
        if self._net_model is None:
            m = self.network.build()
            if not isinstance(m, NetworkFactory):
                raise RecipeError(f"network: model {self.network.name!r} does not lend its networks "
                                  "(build_encoder, build_decoder, latent_size: see fwk.protocols.NetworkFactory)")
            self._net_model = m
        return self._net_model

    def _make_nets(self, template, channels, ctx=None):
        self.nets = self._build_nets(template, channels, ctx)

    def _build_nets(self, template, channels, ctx=None) -> nn.ModuleDict:
        """The network pair(s) for ``channels``, freshly initialised (``_make_nets`` keeps them)."""
        m = self._network_model()
        latent = int(m.latent_size)
        E = len(self.expressions)
        nets = nn.ModuleDict()
        for b, c in enumerate(channels):
            if self.conditional:
                nets[f"b{b}"] = _Net(m.build_encoder(template, c, ctx), m.build_decoder(template, c, ctx, latent + E))
            elif self.mode == "two-step":
                enc = m.build_encoder(template, c, ctx)
                nets[f"b{b}_neutral"] = _Net(enc, m.build_decoder(template, c, ctx))
                nets[f"b{b}"] = _Net(enc, nn.ModuleList(m.build_decoder(template, c, ctx) for _ in range(E)))
            else:
                nets[f"b{b}"] = _Net(nn.ModuleList(m.build_encoder(template, c, ctx) for _ in range(E)),
                                     nn.ModuleList(m.build_decoder(template, c, ctx) for _ in range(E)))
        self._latent_dim = latent
        return nets

    def _latent(self, b, X, sample: bool, only: int | None = None):
        """(codes, kl): codes per expression (list; with ``only``, just that expression's code
        is computed, the others are None) or one shared code."""
        net = self.nets[f"b{b}"]
        if self.conditional or self.mode == "two-step":
            mu, logvar = net.enc(X)
            if self.mode == "two-step":
                return [mu] * len(self.expressions), mu.new_zeros(())  # frozen encoder, latent mean
            z = reparameterize(mu, logvar, sample)
            return [z] * len(self.expressions), kl_divergence(mu, logvar)
        zs, kl = [], 0.0
        for i, enc in enumerate(net.enc):
            if only is not None and i != only:
                zs.append(None)
                continue
            mu, logvar = enc(X)
            zs.append(reparameterize(mu, logvar, sample))
            kl = kl + kl_divergence(mu, logvar)
        return zs, kl

    def _decode(self, b, e, zs):
        """Branch b's decoder output for expression e (an index, or for a conditional model a
        (batch,) tensor of indices: one expression per sample) from the codes ``zs``."""
        net = self.nets[f"b{b}"]
        if self.conditional:
            per_sample = torch.is_tensor(e)
            z = zs if per_sample else zs[e]
            cond = torch.zeros(len(z), len(self.expressions), dtype=z.dtype, device=z.device)
            if per_sample:
                cond[torch.arange(len(z), device=z.device), e] = 1.0
            else:
                cond[:, e] = 1.0
            return net.dec(torch.cat([z, cond], dim=1))
        return net.dec[e](zs[e])

    def _fit_expr_scalers(self, b, F, mask) -> None:
        """Branch b's per-expression scalers: for expression i one ``Scaler.like`` the
        representation's, fitted on the training subjects that have it (F[i] (S, n, c), mask (S, E));
        an expression no training subject has keeps its features as they are."""
        like = self.out_reps[b].scaler
        out = []
        for i, Fi in enumerate(F):
            rows = Fi[mask[:, i]]
            if like is None or len(rows) == 0:
                out.append(Scaler("none").fit(Fi[:1]))
            else:
                out.append(Scaler.like(like).fit(rows))
        self.expr_scalers[b] = out
        self._expr_stacks = {}

    def expr_inverse(self, b, e, G):
        """Network output G (torch, (B, n, c)) of branch b for expression e (an index, or a (B,)
        tensor of indices: one per sample) -> the representation's features (undo the
        per-expression scaling); the identity for a model saved before it existed."""
        if self.expr_scalers is None:
            return G
        if not torch.is_tensor(e):
            return self.expr_scalers[b][e].inverse_torch(G)
        key = (b, G.dtype, G.device)
        if key not in self._expr_stacks:
            sc = self.expr_scalers[b]
            rows = max(x.div.shape[0] for x in sc)  # per vertex (n, c), or (1, c) where one kind is per channel
            self._expr_stacks[key] = tuple(
                torch.as_tensor(np.stack([np.broadcast_to(getattr(x, a), (rows, x.div.shape[1])) for x in sc]),
                                dtype=G.dtype, device=G.device) for a in ("div", "shift"))
        div, shift = self._expr_stacks[key]
        return G * div[e] + shift[e]

    def unscale(self, b, e, G):
        """The loss space of eqs. 5.5 / 5.6: branch b's output for expression e (as ``expr_inverse``)
        in the representation's own units (``Representation.unscale``), differentiable."""
        return self.out_reps[b].unscale(self.expr_inverse(b, e, G))

    # ------------------------------------------------------------------ fitting
    def fit(self, data, ctx) -> None:
        tr, va = data.train, data.val
        names = [s for s in tr.shape_names if s != "neutral"]
        if self.expressions is None:
            self.expressions = [s for s in names if s in (data.shapes or names)] or names
        for e in self.expressions:
            tr.shape_index(e)
        self.template = data.template
        self.in_reps = [_build_rep(s) for s in self.branch_specs]
        self.out_reps = [_build_rep(s) for s in self.branch_specs]
        self._bending = None
        if self.anchor_spec is not None:
            self.anchor = self.anchor_spec.build()
            self.anchor.expressions = list(self.expressions)
            self.anchor.fit(data, ctx)
            missing = [e for e in self.expressions if e not in (self.anchor.expressions or [])]
            if missing:
                raise DataError(f"{self.name}: the anchor ({self.anchor_spec.name}) has no {', '.join(missing)}")
            self._anchor_memo = {}
            if ctx is not None:
                ctx.log(f"[{self.name}] anchor {self.anchor_spec.name}: its prediction of "
                        f"{len(self.expressions)} expression(s) for {len(tr.subjects)} training and "
                        f"{len(va.subjects)} validation neutrals, the reference of every network's features")

        def arrays(col, fit_reps: bool):
            j0 = col.shape_index("neutral")
            keep = col.present[:, j0]
            N = np.asarray(col.positions[keep, j0])
            idx = [col.shape_index(e) for e in self.expressions]
            mask = col.present[keep][:, idx]
            if len(N) == 0:
                return None
            R = self.refs(N, self.expressions)  # what each expression's features are taken against
            X, Y = [], []
            if fit_reps:
                self.expr_scalers = [None] * self.n_branches
            for b in range(self.n_branches):
                if fit_reps:
                    self.in_reps[b].fit(N, None, data.template)
                X.append(torch.as_tensor(self.in_reps[b].encode(N)))
            for b in range(self.n_branches):
                if fit_reps:
                    has = mask.any(1)
                    Pe = np.concatenate([np.asarray(col.positions[keep, j])[mask[:, i]] for i, j in enumerate(idx)])
                    Ne = np.concatenate([R[e][mask[:, i]] for i, e in enumerate(self.expressions)])
                    if len(Pe) == 0 or not has.any():
                        raise DataError(f"{self.name}: no training subject has any of {', '.join(self.expressions)}")
                    self.out_reps[b].fit(Pe, Ne, data.template)
                F = []
                for i, j in enumerate(idx):
                    Ri = R[self.expressions[i]]
                    Pj = np.asarray(col.positions[keep, j]).copy()
                    Pj[~mask[:, i]] = Ri[~mask[:, i]]  # missing shapes: any finite stand-in, masked out of the loss
                    F.append(self.out_reps[b].encode(Pj, Ri))
                if fit_reps:
                    self._fit_expr_scalers(b, F, mask)
                for i in range(len(F)):  # each expression's features released once scaled (a rig has 57)
                    Y.append(torch.as_tensor(self.expr_scalers[b][i].transform(F[i]).astype(np.float32)))
                    F[i] = None
            del R
            return X, Y, torch.as_tensor(mask), N

        train = arrays(tr, True)
        if train is None:
            raise DataError(f"{self.name}: the training split has no neutrals")
        val = arrays(va, False)
        X, Y, mask, N = train
        channels = [x.shape[-1] for x in X]
        self.shape = (data.template.n_vertices, channels)
        engine.seed_everything(ctx.seed)
        self._make_nets(data.template, channels, ctx)
        config = ctx.train.replace(**self.train_overrides)
        kl = config.kl_weight if self.kl_weight is None else self.kl_weight
        if self.mode == "two-step":
            # step 1: a VAE on every training neutral (with or without expressions), then frozen
            j0 = tr.shape_index("neutral")
            for b in range(self.n_branches):
                Nall = np.asarray(tr.positions[tr.present[:, j0], j0])
                Fn = torch.as_tensor(self.in_reps[b].encode(Nall))
                Fv = val[0][b] if val is not None else None
                engine.fit(autoencoder_module(self.nets[f"b{b}_neutral"], self.in_reps[b].unscale, kl), Fn, Fv, ctx,
                    f"{self.name}-step1-{self.branch_names[b]}", config)
                for p in self.nets[f"b{b}"].enc.parameters():
                    p.requires_grad_(False)
        self.nets.train()
        if self.conditional:  # batches of (subject, expression) pairs: batch_size pairs per step
            train_t = _pairs(X, Y, mask)
            val_t = _pairs(*val[:3]) if val is not None and bool(val[2].any()) else None
            module = _conditional_module(self, kl, self.name)
        else:
            train_t = (*X, *Y, mask)
            val_t = (*val[0], *val[1], val[2]) if val is not None else None
            module = _joint_module(self, kl, self.name)
        engine.fit(module, train_t, val_t, ctx, f"{self.name}-step2" if self.mode == "two-step" else self.name,
                   config)
        self.nets.eval()

    # ------------------------------------------------------------------ inference
    def _check(self, neutrals, expression):
        if self.nets is None:
            raise RuntimeError(f"{self.name}: not fitted")
        if expression not in self.expressions:
            raise DataError(f"{self.name}: not trained for expression {expression!r} (trained: {', '.join(self.expressions)})")
        N = np.asarray(neutrals, dtype=np.float64)
        if N.ndim == 2:
            N = N[None]
        if N.shape[1:] != (self.shape[0], 3):
            raise DataError(f"{self.name}: neutrals of shape {N.shape[1:]}, trained on {self.shape[0]} vertices")
        return N

    @torch.no_grad()
    def branch_features(self, N, expression: str, b: int) -> np.ndarray:
        """Network output F'_expr (b, n, c) of branch b for neutrals N in the evaluation space."""
        e = self.expressions.index(expression)
        X = torch.as_tensor(self.in_reps[b].encode(N))
        zs, _ = self._latent(b, X, sample=False, only=e)
        return self.expr_inverse(b, e, self._decode(b, e, zs)).numpy()

    def branch_predict(self, N, expression: str, b: int, target=None) -> np.ndarray:
        """Eq. 5.7: P'_expr = g^-1(F'_expr) relative to the neutral (dr integrated against it), or
        with an ``anchor`` relative to the anchor's prediction for the neutral."""
        R = self.refs(N, [expression])[expression]
        return self.out_reps[b].decode(self.branch_features(N, expression, b), R, target)

    def predict_all(self, neutrals, expressions: list[str], target: dict | None = None) -> dict:
        """{expression: ``predict(neutrals, expression, target[expression])``} (``target``:
        {expression: ground truth}, optional, as in ``predict``): one network pass per expression,
        or, for a conditional model, one encoder pass and one decoder pass over every expression
        at once (``predict_many``; the same values up to float32 rounding, tested)."""
        target = target or {}
        if self.conditional and len(expressions) > 1:
            return self.predict_many(neutrals, list(expressions), target)
        return {e: self.predict(neutrals, e, target.get(e)) for e in expressions}

    @torch.no_grad()
    def branch_features_many(self, N, expressions: list[str], b: int, batch: int = 64) -> dict:
        """{expression: (b, n, c)} network outputs of branch b of a conditional model: the code of
        each neutral computed once, decoded with every expression's condition in batches of
        ``batch`` meshes (``branch_features`` one expression at a time)."""
        idx = [self.expressions.index(e) for e in expressions]
        X = torch.as_tensor(self.in_reps[b].encode(N))
        zs, _ = self._latent(b, X, sample=False)
        z = zs[0]  # conditional: one code for every expression
        nb = len(z)
        out = {}
        per = max(1, batch // max(nb, 1))  # expressions per decoder call
        for s in range(0, len(expressions), per):
            chunk = idx[s:s + per]
            zz = z.repeat(len(chunk), 1)  # (len(chunk) * nb, latent), expression-major
            ei = torch.as_tensor(chunk).repeat_interleave(nb)
            F = self.expr_inverse(b, ei, self._decode(b, ei, zz)).numpy()
            for j, e in enumerate(expressions[s:s + per]):
                out[e] = F[j * nb:(j + 1) * nb]
        return out

    def branch_predict_many(self, N, expressions: list[str], b: int, target: dict | None = None) -> dict:
        """{expression: eq. 5.7's P'_expr} for a conditional model (``branch_predict`` batched)."""
        F = self.branch_features_many(N, expressions, b)
        target = target or {}
        R = self.refs(N, expressions)
        return {e: self.out_reps[b].decode(F[e], R[e], target.get(e)) for e in expressions}

    def predict_many(self, neutrals, expressions: list[str], target: dict) -> dict:
        """``predict_all`` of a conditional model, batched over the expressions."""
        for e in expressions:
            N = self._check(neutrals, e)
        return self.branch_predict_many(N, expressions, 0, target)

    # ------------------------------------------------------------------ saving
    def _base_state(self) -> dict:
        return {"expressions": self.expressions, "nets": self.nets.state_dict(), "shape": self.shape,
                "in_reps": [r.state_dict() for r in self.in_reps], "out_reps": [r.state_dict() for r in self.out_reps],
                "expr_scalers": None if self.expr_scalers is None else [[x.state_dict() for x in sc]
                                                                        for sc in self.expr_scalers],
                "template_vertices": self.template.vertices, "template_triangles": self.template.triangles,
                **({} if self.anchor is None else {"anchor": self.anchor.state_dict()})}

    def _load_base(self, d: dict, ctx=None) -> None:
        self.expressions = list(d["expressions"])
        self.shape = (int(d["shape"][0]), list(d["shape"][1]))
        self.template = Template(np.asarray(d["template_vertices"]), np.asarray(d["template_triangles"]))
        self.in_reps = [_build_rep(s) for s in self.branch_specs]
        self.out_reps = [_build_rep(s) for s in self.branch_specs]
        for r, s in zip(self.in_reps, d["in_reps"]):
            r.load_state_dict(s, ctx=ctx)
        for r, s in zip(self.out_reps, d["out_reps"]):
            r.load_state_dict(s, ctx=ctx)
        es = d.get("expr_scalers")  # None in a model saved before the per-expression scaling: pooled
        self.expr_scalers = None if es is None else [[Scaler().load_state_dict(x) for x in sc] for sc in es]
        self._expr_stacks = {}
        self._make_nets(self.template, self.shape[1], ctx)
        # a packed state leaves out the buffers the networks derive from the template (pooling
        # matrices, spiral indices: ``derived_buffers``); every parameter must be there
        got = self.nets.load_state_dict(d["nets"], strict=False)
        buffers = {k for k, _ in self.nets.named_buffers()}
        lost = [k for k in got.missing_keys if k not in buffers]
        if got.unexpected_keys or lost:
            raise DataError(f"{self.name}: the saved networks do not fit the recipe's (missing "
                            f"{', '.join(lost[:3]) or 'none'}; unexpected {', '.join(got.unexpected_keys[:3]) or 'none'})")
        self.nets.eval()
        self._anchor_memo, self._bending, self.anchor = {}, None, None
        if self.anchor_spec is not None:
            if d.get("anchor") is None:
                raise DataError(f"{self.name}: the recipe gives an anchor ({self.anchor_spec.name}) but the saved "
                                "model has none")
            self.anchor = self.anchor_spec.build()
            self.anchor.load_state_dict(d["anchor"], ctx=ctx)


class PB(_Blend):
    """Personalised blendshapes: a graph VAE from the neutral to each expression (end-to-end or two-step)."""

    name = "pb"

    def __init__(self, representation: Annotated[Spec, Kind("representation")] = "euclidean",
                 network: Annotated[Spec, Kind("model", NetworkFactory)] = "vae", mode: str = "end-to-end",
                 expressions: list[str] | None = None, conditional: bool = False,
                 kl_weight: float | None = None, train: dict | None = None,
                 anchor: Annotated[Spec | None, Kind("model", BlendshapeModel)] = None, bending_weight: float = 0.0):
        if anchor is not None and mode != "end-to-end":
            raise RecipeError("anchor: only with mode end-to-end")
        self._init(network, [representation], mode, expressions, conditional, kl_weight, train, anchor,
                   bending_weight)
        self.branch_names = [self.branch_specs[0].name]

    def describe(self) -> str:
        """A report's legend line (``fwk.protocols.Described``)."""
        rep = self.branch_specs[0]
        what = " ".join(x for x in (rep.name, rep.params.get("scaling")) if x)
        return f"PB (thesis 5.2): a graph VAE from the neutral to each expression, {self.mode}, {what}" + \
            self._describe_extras()

    @property
    def places_rigidly(self) -> bool:
        """Whether the output representation loses the rigid placement (dr): ``predict`` then
        places the prediction onto ``target`` when one is given (the thesis's scoring)."""
        return bool(self.branch_specs[0].cls.places_rigidly)

    def predict(self, neutrals, expression: str, target=None) -> np.ndarray:
        """(b, n, 3) neutrals -> (b, n, 3) the expression (``target``: ground truth that a ``dr``
        output is rigidly registered onto, the thesis's evaluation protocol; None at inference)."""
        N = self._check(neutrals, expression)
        return self.branch_predict(N, expression, 0, target)

    def state_dict(self) -> dict:
        return {"kind": self.name, **self._base_state()}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore; ``ctx`` (optional) lends its cache to the network's graph hierarchy."""
        self._load_base(d, ctx)


class PBS(_Blend):
    """PB with spectral assembly: a euclidean and a dr PB combined per expression at a Pareto-optimal k."""

    name = "pbs"
    # the cut-selecting role's members, declared on the class (read-only; every instance sets its own)
    k: dict[str, int] = MappingProxyType({})
    sweep: dict = MappingProxyType({})

    def __init__(self, spatial: Annotated[Spec, Kind("representation")] = "euclidean",
                 differential: Annotated[Spec, Kind("representation")] = "dr",
                 network: Annotated[Spec, Kind("model", NetworkFactory)] = "vae",
                 assembler: Annotated[Spec, Kind("assembler")] = "spectral",
                 expressions: list[str] | None = None,
                 conditional: bool = False, k: int | dict[str, int] | None = None, ks: list[int] | None = None,
                 knee_metric: str = "fmpd", sweep_metrics: list[str] = ("l1", "dame", "fmpd"),
                 distance_metric: str = "l1", kl_weight: float | None = None, train: dict | None = None,
                 anchor: Annotated[Spec | None, Kind("model", BlendshapeModel)] = None, bending_weight: float = 0.0):
        self._init(network, [spatial, differential], "end-to-end", expressions, conditional, kl_weight, train,
                   anchor, bending_weight)
        self.branch_names = ["spatial", "differential"]
        self.assembler_spec = make_spec("assembler", assembler, "assembler")
        self.k_fixed, self.ks_param = k, ks
        self.knee_metric, self.distance_metric = knee_metric, distance_metric
        self.sweep_metrics = list(sweep_metrics)
        for key, m in (("knee_metric", knee_metric), ("distance_metric", distance_metric)):
            if m not in self.sweep_metrics:
                raise RecipeError(f"{key}: {m!r} must be one of sweep_metrics ({', '.join(self.sweep_metrics)})")
        self.k: dict[str, int] = {}
        self.sweep: dict = {}
        self.assembler = None
        self.assembler_k = 0  # the largest cut the assembler was built for

    def describe(self) -> str:
        """A report's legend line (``fwk.protocols.Described``)."""
        s, d = self.branch_specs
        k = "k fixed" if self.k_fixed is not None else f"k at the ({self.distance_metric.upper()}, " \
            f"{self.knee_metric.upper()}) knee on validation"
        head = "DT-anchored PBS" if self.anchor_spec is not None else "PBS (thesis 5.3)"
        def rep(r):
            return " ".join(x for x in (r.name, r.params.get("scaling")) if x)
        return (f"{head}: a {rep(s)} and a {rep(d)} PB network spectrally assembled, {k}" + self._describe_extras())

    # ------------------------------------------------------------------ assembly
    def _ks(self, n: int) -> list[int]:
        ks = sorted({min(int(k), n) for k in self.ks_param}) if self.ks_param else thesis_ks(n)
        if any(k < 0 for k in ks):
            raise RecipeError("ks: k values must be >= 0")
        return ks

    def _fit_assembler(self, template, kmax: int, cache=None):
        n = template.n_vertices
        kmax = int(min(kmax, n - 1))
        if self.assembler is not None and self.assembler_k >= kmax:
            return
        if kmax <= 0:
            self.assembler, self.assembler_k = None, 0
            return
        a = self.assembler_spec.build(k=kmax)  # the Assembler role: a constructor taking the cut k
        a.fit(template, template.vertices, cache=cache)
        self.assembler, self.assembler_k = a, kmax

    def branches(self, N, expression: str):
        """(P'_spatial, P'_diff): both networks' predictions in positions; the differential one
        placed by a rigid fit onto the spatial one (no ground truth needed)."""
        Ps = self.branch_predict(N, expression, 0)
        Pd = self.branch_predict(N, expression, 1, target=Ps)
        return Ps, Pd

    def assemble(self, Ps, Pd, ks) -> np.ndarray:
        """Eq. 5.10 for every k in ks: (len(ks), b, n, 3); k = 0 -> P'_diff, k >= n -> P'_spatial."""
        n = Ps.shape[1]
        out = np.empty((len(ks), *Ps.shape))
        inner = [i for i, k in enumerate(ks) if 0 < k < n]
        for i, k in enumerate(ks):
            if k <= 0:
                out[i] = Pd
            elif k >= n:
                out[i] = Ps
        if inner:
            out[inner] = self.assembler.assemble_many([Ps, Pd], [ks[i] for i in inner])
        return out

    def predict_many(self, neutrals, expressions: list[str], target: dict) -> dict:
        """``predict_all`` of a conditional PBS, batched over the expressions: both networks'
        outputs for every expression (the dr one placed onto the spatial one, as ``branches``),
        assembled at each expression's k."""
        for e in expressions:
            N = self._check(neutrals, e)
        Ps = self.branch_predict_many(N, expressions, 0)
        Pd = self.branch_predict_many(N, expressions, 1, target=Ps)
        by_k: dict[int, list[str]] = {}
        for e in expressions:  # expressions sharing a k: one assembly call over all their meshes
            by_k.setdefault(int(self.k.get(e, self.shape[0])), []).append(e)
        out = {}
        for k, es in by_k.items():
            A = self.assemble(np.concatenate([Ps[e] for e in es]), np.concatenate([Pd[e] for e in es]), [k])[0]
            for i, e in enumerate(es):
                out[e] = A[i * len(N):(i + 1) * len(N)]
        return {e: out[e] for e in expressions}

    def predict(self, neutrals, expression: str, target=None, k: int | None = None) -> np.ndarray:
        """(b, n, 3) neutrals -> the expression at the chosen k (``target`` is not used: PBS
        needs no ground truth)."""
        N = self._check(neutrals, expression)
        k = self.k.get(expression, self.shape[0]) if k is None else int(k)
        Ps, Pd = self.branches(N, expression)
        return self.assemble(Ps, Pd, [k])[0]

    def single(self, b: int) -> PB:
        """Branch b (0 spatial, 1 differential) as a single end-to-end ``pb`` model sharing
        this model's fitted representations and networks."""
        pb = PB(representation=self.branch_specs[b], network=self.network, conditional=self.conditional,
                anchor=self.anchor_spec)
        pb.expressions, pb.template, pb._net_model = list(self.expressions), self.template, self._net_model
        pb.anchor, pb._anchor_memo = self.anchor, self._anchor_memo
        pb.shape = (self.shape[0], [self.shape[1][b]])
        pb.in_reps, pb.out_reps = [self.in_reps[b]], [self.out_reps[b]]
        pb.expr_scalers = None if self.expr_scalers is None else [self.expr_scalers[b]]
        pb.nets = nn.ModuleDict({"b0": self.nets[f"b{b}"]})
        return pb

    def part_models(self) -> dict:
        """The two single end-to-end PBs inside PBS (``fwk.protocols.CompositeModel``), labelled
        ``pb-<representation>-<scaling>``: the spatial network first, then the dr one."""
        return {f"pb-{s.name}-{s.params.get('scaling', 'std' if b == 0 else 'norm')}": self.single(b)
                for b, s in enumerate(self.branch_specs)}

    def parts(self, neutrals, expression: str, target=None) -> dict:
        """The two single end-to-end PB predictions inside PBS (``part_models``): the spatial one
        (k = n) and the dr one registered onto ``target`` when given, as the thesis evaluates dr
        outputs."""
        N = self._check(neutrals, expression)
        (a, spatial), (b, differential) = self.part_models().items()
        return {a: spatial.predict(N, expression), b: differential.predict(N, expression, target)}

    # ------------------------------------------------------------------ k selection
    def fit(self, data, ctx) -> None:
        super().fit(data, ctx)
        n = data.template.n_vertices
        ks = self._ks(n)
        fixed = self.k_fixed
        self._fit_assembler(data.template, max([k for k in ks if k < n] + ([fixed] if isinstance(fixed, int) else
                                                                        list((fixed or {}).values())) + [1]),
                            ctx.cache)
        if fixed is not None:
            self.k = {e: int(fixed if isinstance(fixed, int) else fixed.get(e, n)) for e in self.expressions}
            self.sweep = {}
            return
        self.select_k(data.val, ks, ctx)

    def select_k(self, col, ks, ctx=None) -> dict:
        """Sweep ks on the subjects of ``col`` (validation), per expression: metrics, Pareto
        front of (distance_metric, knee_metric), knee. Sets and returns ``self.k``."""
        metrics = [make_spec("metric", m, "sweep_metrics").build() for m in self.sweep_metrics]
        dist = self.distance_metric
        j0 = col.shape_index("neutral")
        self.sweep = {}
        for e in self.expressions:
            je = col.shape_index(e)
            ok = col.present[:, j0] & col.present[:, je]
            if not ok.any():
                self.k[e] = int(ks[-1])
                if ctx is not None:
                    ctx.log(f"[{self.name}] {e}: no validation subject, k = {self.k[e]}")
                continue
            N, G = np.asarray(col.positions[ok, j0]), np.asarray(col.positions[ok, je])
            Ps, Pd = self.branches(N, e)
            allP = self.assemble(Ps, Pd, ks)
            scores = {m.name: [] for m in metrics}
            for P in allP:
                res = evaluate(P, G, self.template, metrics)
                for m in metrics:
                    scores[m.name].append(float(res[m.name]["scores"].mean()))
            entry = {"ks": list(map(int, ks)), **{k: v for k, v in scores.items()}, "n_subjects": int(ok.sum())}
            for pm in [m for m in self.sweep_metrics if m != dist]:
                pts = np.stack([scores[dist], scores[pm]], 1)
                entry[f"front_{pm}"] = [int(ks[i]) for i in pareto_front(pts)]
            front = pareto_front(np.stack([scores[dist], scores[self.knee_metric]], 1))
            i = front[knee(np.asarray(scores[dist])[front], np.asarray(scores[self.knee_metric])[front])]
            self.k[e] = int(ks[i])
            entry["chosen"] = self.k[e]
            entry["knee_metric"] = self.knee_metric
            self.sweep[e] = entry
            if ctx is not None:
                ctx.log(f"[{self.name}] {e}: Pareto front ({dist.upper()}, {self.knee_metric.upper()}) at k = "
                        f"{[int(ks[j]) for j in front]}, knee k = {self.k[e]}")
        return self.k

    def state_dict(self) -> dict:
        return {"kind": self.name, **self._base_state(), "k": dict(self.k), "sweep": self.sweep,
                "assembler": None if self.assembler is None else self.assembler.state_dict(),
                "assembler_k": self.assembler_k}

    def derived_buffers(self) -> set[str]:
        """The networks' buffers that networks built afresh from the template hold too, equal
        (pooling matrices, spiral indices: derived from the graph hierarchy, not trained)."""
        with torch.random.fork_rng():  # building initialises weights: the caller's random state stays as it was
            fresh = dict(self._build_nets(self.template, self.shape[1]).named_buffers())
        out = set()
        for k, v in self.nets.named_buffers():
            f = fresh.get(k)
            if f is None or f.shape != v.shape or f.dtype != v.dtype or f.layout != v.layout:
                continue
            if v.layout == torch.sparse_coo:
                a, b = v.coalesce(), f.coalesce()
                same = torch.equal(a.indices(), b.indices()) and torch.equal(a.values(), b.values())
            else:
                same = torch.equal(v, f)
            if same:
                out.add(k)
        return out

    def packed_state(self) -> dict:
        """The state ``fwk pack`` ships (``fwk.protocols.Packable``): ``state_dict()`` without the
        k sweep's curves (reports read them, prediction does not; the chosen k stay), without the
        networks' buffers that building them from the template gives again (``derived_buffers``),
        with the assembler's basis cut at the largest chosen k below n (``TruncatesCuts``; none
        when every chosen k is 0 or n); the anchor's own packed state when it has one."""
        st = self.state_dict()
        st["sweep"] = {}
        derived = self.derived_buffers()
        st["nets"] = {k: v for k, v in st["nets"].items() if k not in derived}
        n = self.shape[0]
        K = max([int(k) for k in self.k.values() if 0 < int(k) < n], default=0)
        if self.assembler is not None and K == 0:
            st["assembler"], st["assembler_k"] = None, 0
        elif self.assembler is not None and K < self.assembler_k and isinstance(self.assembler, TruncatesCuts):
            st["assembler"], st["assembler_k"] = self.assembler.truncated_state(K), K
        if self.anchor is not None and isinstance(self.anchor, Packable):
            st["anchor"] = self.anchor.packed_state()
        return st

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore; ``ctx`` (optional) lends its cache to the network's graph hierarchy."""
        self._load_base(d, ctx)
        self.k = {str(k): int(v) for k, v in d["k"].items()}
        self.sweep = d.get("sweep", {})
        self.assembler, self.assembler_k = None, 0
        if d.get("assembler") is not None:
            # the cut the assembler was built with (models saved before it was kept: the built-in
            # spectral assembler's own record of its cuts)
            self.assembler_k = int(d["assembler_k"]) if "assembler_k" in d else int(d["assembler"]["cuts"][-1])
            self.assembler = self.assembler_spec.build(k=self.assembler_k)
            self.assembler.load_state_dict(d["assembler"], ctx=ctx)


@hookimpl
def fwk_register_models():
    return [PB, PBS]
