"""Model ``dt``: Deformation Transfer (Sumner & Popović 2004) between meshes of one topology,
the industry's baseline for personalised blendshapes (thesis 5.2.3).

A source identity gives, for each expression e, per-triangle affine maps Q_j = V~_j V_j^-1,
where V_j = [v2 - v1, v3 - v1, v4 - v1] on the source neutral and V~_j the same on the source
expression, with the fourth vertex v4 = v1 + n / sqrt(|n|) (n = (v2 - v1) x (v3 - v1), Sumner's
choice, which makes V_j invertible and scales like an edge). For a target neutral with the same
construction W0_j, the expression x (n vertices, plus one free fourth vertex per triangle)
minimises

    sum_j || W_j(x) W0_j^-1 - Q_j ||_F^2

a sparse linear least-squares problem A x = c with A (3m x (n + m)) depending only on the target
neutral: its normal equations A^T A are factorised once per target (SuperLU ordered for
symmetry, ``fwk.geometry.factor_spd``) and reused for every expression and every coordinate.
The translation is fixed by pinning one vertex per
connected component at its neutral position moved by the source's displacement there, then the
centroid of the result is placed at the target's neutral centroid moved by the source's
centroid displacement (in fwk's registered, centred space the two agree with an exact affine
transfer). ``placement: median`` (beyond the thesis) places it instead by the per-coordinate median
over the vertices of (T0 + d - X), d the source's displacement and X the solved result: the L1
translation, which a majority of the vertices decides. Where the source leaves most of a head
still (a jaw opening: the skull, the forehead), those vertices then stay still on the target too;
the centroid rule moves them by the difference of the two centroid shifts. On fwk's ICT-FaceKit
data, whose synthetic personalisation moves most vertices a little under every expression, it
halves the skull top's motion under jawOpen from the mean subject (0.077 / 0.069 / 0.026 cm with
the centroid, 0.042 / 0.026 / 0.008 cm with the median, three test identities; ICT's own shape:
under 0.001 cm); what is left is the least-squares solve's own deformation. Several sources (``sources: [0, 1, 2]``) average their per-triangle maps Q_j; the
thesis reports each source separately (one ``dt`` per source in a recipe).

``sources: mean`` (beyond the thesis) takes as the one source the mean training subject: the
neutral N = mean over the training subjects s of N_s and, per expression e, E = mean over the
subjects that have e of E_s (in fwk's registered, centred, scaled space, where the subjects are
aligned). The state then holds only these means (statistics of the training set, as a PCA
model's mean), no subject's own meshes: the form of anchor a model that ships without its
training data can carry. It is not the average of the subjects' maps (``sources: [0, 1, ...]``):
the maps of the mean meshes.

Properties (tested): with source = target the source expression comes back exactly; a global
rigid or similarity source deformation of a centred mesh is transferred exactly to any centred
target. A general affine map (a shear) is transferred exactly only onto the source mesh itself:
Sumner's fourth vertex n / sqrt|n| is not affine-covariant (a shear does not map normals to
normals), so Q_j equals the map only on the source triangle's plane; onto another head the
error stays within 2% of the head's size (tested), as in every Sumner-style implementation.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from fwk.errors import DataError, RecipeError
from fwk.geometry import factor_spd
from fwk.hookspecs import hookimpl
from fwk.protocols import BLENDSHAPES


def frames(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(b, m, 3, 3) matrices [v2 - v1, v3 - v1, v4 - v1] (as columns) of every triangle."""
    e1 = V[:, F[:, 1]] - V[:, F[:, 0]]
    e2 = V[:, F[:, 2]] - V[:, F[:, 0]]
    n = np.cross(e1, e2)
    e3 = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300))
    return np.stack([e1, e2, e3], axis=-1)


#: ``sources: mean``: the mean training subject as the one source
MEAN = "mean"


class TargetSystem:
    """The factorised normal equations of one target neutral."""

    def __init__(self, T0: np.ndarray, F: np.ndarray):
        n, m = len(T0), len(F)
        W0 = frames(T0[None], F)[0]
        Winv = np.linalg.inv(W0)  # (m, 3, 3)
        # T_j^T = Winv^T [x2 - x1; x3 - x1; x4 - x1]: row r of T_j^T = sum_k Winv[k, r] (x_{k+1} - x_1)
        G = np.transpose(Winv, (0, 2, 1))  # G[j, r, k] = Winv[j, k, r]
        cols = np.stack([F[:, 0], F[:, 1], F[:, 2], n + np.arange(m)], axis=1)  # (m, 4)
        coef = np.concatenate([-G.sum(-1, keepdims=True), G], axis=-1)  # (m, 3, 4)
        rows = np.repeat(np.arange(3 * m), 4)
        A = sp.csr_matrix((coef.reshape(-1), (rows, np.repeat(cols, 3, axis=0).reshape(-1))), shape=(3 * m, n + m))
        self.A = A
        self.n, self.m, self.F, self.T0 = n, m, F, T0
        adj = sp.coo_matrix((np.ones(3 * m), (F[:, [0, 1, 2]].ravel(), F[:, [1, 2, 0]].ravel())), shape=(n, n))
        _, labels = connected_components(adj, directed=False)
        self.pins = np.array([np.flatnonzero(labels == c)[0] for c in range(labels.max() + 1)])
        free = np.ones(n + m, bool)
        free[self.pins] = False
        self.free = np.flatnonzero(free)
        Af = A[:, self.free].tocsc()
        self.Ap = A[:, self.pins]
        self.Af = Af
        self.lu = factor_spd(Af.T @ Af)  # symmetric positive definite: 3.6x faster than COLAMD

    def solve(self, Q: np.ndarray, pin_pos: np.ndarray) -> np.ndarray:
        """Q (m, 3, 3) target gradients; pin_pos (len(pins), 3) -> (n, 3) vertices."""
        c = np.transpose(Q, (0, 2, 1)).reshape(3 * self.m, 3)  # rows of T_j^T
        c = c - self.Ap @ pin_pos
        x = self.lu.solve(self.Af.T @ c)
        out = np.empty((self.n + self.m, 3))
        out[self.free] = x
        out[self.pins] = pin_pos
        return out[: self.n]


class DeformationTransfer:
    """Deformation Transfer (Sumner & Popović 2004): the no-training blendshape baseline."""

    name = "dt"
    task_family = BLENDSHAPES
    expressions: list[str] | None = None  # the blendshape role's member, declared on the class; set per instance

    def __init__(self, sources: int | list[int] | Literal["mean"] = 0,
                 placement: Literal["centroid", "median"] = "centroid"):
        self.sources = MEAN if sources == MEAN else ([sources] if isinstance(sources, int) else list(sources))
        self.placement = placement
        if not self.sources:
            raise RecipeError("sources: at least one source subject index")
        self.expressions = None
        self.F = None
        self.src = {}  # expression -> (neutral (s, n, 3), expression (s, n, 3))
        self._maps = {}  # expression -> the sources' (Q, displacement, its centroid): see _source_maps
        self._inv = (None, None)  # (the source neutrals, the inverses of their frames): see gradients

    def describe(self) -> str:
        """A report's legend line (``fwk.protocols.Described``): the source subject(s)."""
        line = self._describe_sources()
        return line if self.placement == "centroid" else line + "; placed by the median vertex"

    def _describe_sources(self) -> str:
        if self.sources == MEAN:
            return ("Deformation Transfer (Sumner & Popović 2004) from the mean training subject (the training "
                    "neutrals' mean and each expression's mean) as the source: no training")
        if len(self.sources) == 1:
            return (f"Deformation Transfer (Sumner & Popović 2004) from training subject {self.sources[0]} "
                    "as the source: no training")
        return (f"Deformation Transfer (Sumner & Popović 2004) from training subjects "
                f"{', '.join(map(str, self.sources))} as the sources (their per-triangle maps averaged): no training")

    def fit(self, data, ctx=None) -> None:
        """Keep the source subjects' neutral and expressions (of ``expressions`` when set, else
        every expression of the training split); afterwards ``expressions`` lists those with a
        source."""
        col = data.train
        self.F = np.asarray(data.template.triangles)
        wanted = None if self.expressions is None else set(self.expressions)
        if self.sources == MEAN:
            self.src = {}
            N = np.asarray(col.positions[:, 0]).mean(axis=0)[None]
            for j, e in enumerate(col.shape_names):
                ok = col.present[:, j]
                if e == "neutral" or (wanted is not None and e not in wanted) or not ok.any():
                    continue
                self.src[e] = (N, np.asarray(col.positions[ok, j]).mean(axis=0)[None])
            self.expressions = list(self.src)
            self._maps, self._inv = {}, (None, None)
            return
        if max(self.sources) >= len(col.subjects):
            raise RecipeError(f"sources: index {max(self.sources)} but the training split has {len(col.subjects)} subjects")
        N = np.asarray(col.positions[self.sources, 0])
        self.src = {}
        for j, e in enumerate(col.shape_names):
            if e == "neutral" or (wanted is not None and e not in wanted):
                continue
            ok = col.present[self.sources, j]
            if ok.any():
                self.src[e] = (N[ok], np.asarray(col.positions[self.sources, j])[ok])
        self.expressions = list(self.src)
        self._maps, self._inv = {}, (None, None)

    def gradients(self, expression: str) -> np.ndarray:
        """The source's per-triangle maps Q_j (m, 3, 3) for ``expression``, averaged over sources."""
        if expression not in self.src:
            raise RecipeError(f"{self.name}: no source for expression {expression!r} (have: {', '.join(self.src)})")
        S0, S1 = self.src[expression]
        if self._inv[0] is not S0:  # sources: mean shares one neutral among every expression: one inverse
            self._inv = (S0, np.linalg.inv(frames(S0, self.F)))
        Q = frames(S1, self.F) @ self._inv[1]
        return Q.mean(axis=0)

    def _transfer_one(self, T0: np.ndarray, system: TargetSystem, expression: str) -> np.ndarray:
        """One target neutral (n, 3), its factorised system -> (n, 3) the expression transferred."""
        Q, disp, cdisp = self._source_maps(expression)
        X = system.solve(Q, T0[system.pins] + disp[system.pins])
        if self.placement == "median":  # the median vertex moves as the source's does there
            return X + np.median(T0 + disp - X, axis=0)
        return X - X.mean(0) + T0.mean(0) + cdisp

    def _source_maps(self, expression: str):
        """(Q (m, 3, 3), the sources' mean displacement (n, 3), its centroid (3,)), kept per
        expression: the same for every target."""
        if expression not in self._maps:
            S0, S1 = self.src.get(expression, (None, None))
            Q = self.gradients(expression)
            disp = (S1 - S0).mean(axis=0)
            self._maps[expression] = (Q, disp, disp.mean(axis=0))
        return self._maps[expression]

    def predict(self, neutrals, expression: str, target=None) -> np.ndarray:
        """(b, n, 3) neutrals -> (b, n, 3) the expression transferred (``target`` is not used:
        DT needs no ground truth)."""
        return self.predict_all(neutrals, [expression])[expression]

    def predict_all(self, neutrals, expressions: list[str], target: dict | None = None) -> dict:
        """Every expression for every neutral: one factorisation per neutral, reused for every
        expression and released before the next neutral's (memory stays that of one system,
        whatever the number of neutrals)."""
        neutrals = np.asarray(neutrals, dtype=np.float64)
        for e in expressions:
            self._source_maps(e)  # an unknown expression is refused before any factorisation
        out = {e: np.empty_like(neutrals) for e in expressions}
        for i, T0 in enumerate(neutrals):
            system = TargetSystem(T0, self.F)
            for e in expressions:
                out[e][i] = self._transfer_one(T0, system, e)
        return out

    def state_dict(self) -> dict:
        if self.sources == MEAN and self.src:  # the one mean neutral once, not once per expression
            N = next(iter(self.src.values()))[0]
            return {"sources": MEAN, "F": self.F, "neutral": N, "expressions": {e: E for e, (_, E) in self.src.items()}}
        return {"sources": self.sources, "F": self.F, "src": self.src}

    def packed_state(self) -> dict:
        """The state ``fwk pack`` ships (``fwk.protocols.Packable``). ``sources: mean``: the mean
        neutral and, per expression, only the vertices the mean expression moves (a bit mask; a
        blendshape leaves much of a face exactly where it is) with their offsets from the neutral,
        which ``load_state_dict`` adds back onto the neutral (lossless: no rounding beyond the
        storage's float type; measured on the ICT rig, rounding the offsets to 16-bit steps of the
        largest one moved DT's output by 7.6e-5 cm and its DAME by up to 1.4 %); other sources:
        ``state_dict()``."""
        if self.sources != MEAN or not self.src:
            return self.state_dict()
        N = next(iter(self.src.values()))[0]
        moved = {}
        for e, (_, E) in self.src.items():
            D = E[0] - N[0]
            mask = np.any(D != 0, axis=1)
            moved[e] = {"mask": np.packbits(mask), "offsets": D[mask]}
        return {"sources": MEAN, "F": self.F, "neutral": N, "moved": moved}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore (``ctx`` is not needed: DT keeps arrays only). ``sources: mean`` stores its
        mean neutral once beside the mean expressions; a state with ``src`` (every source's
        neutral and expression per expression, as ``sources: mean`` was saved before) loads too."""
        self.sources = MEAN if d["sources"] == MEAN else list(d["sources"])
        self.F = np.asarray(d["F"])
        if "src" in d:
            self.src = dict(d["src"])
        elif "moved" in d:  # packed: the moved vertices' offsets onto the mean neutral
            N = np.asarray(d["neutral"], dtype=np.float64)
            self.src = {}
            n = N.shape[1]
            for e, mv in d["moved"].items():
                mask = np.unpackbits(np.asarray(mv["mask"], dtype=np.uint8), count=n).astype(bool)
                offsets = np.asarray(mv["offsets"], dtype=np.float64)
                if offsets.shape != (int(mask.sum()), 3):
                    raise DataError(f"dt: expression {e!s}: {offsets.shape} offsets for {int(mask.sum())} moved vertices")
                E = N.copy()
                E[0, mask] += offsets
                self.src[str(e)] = (N, E)
        else:
            N = np.asarray(d["neutral"])
            self.src = {str(e): (N, np.asarray(E)) for e, E in d["expressions"].items()}
        self.expressions = list(self.src)
        self._maps, self._inv = {}, (None, None)


@hookimpl
def fwk_register_models():
    return [DeformationTransfer]
