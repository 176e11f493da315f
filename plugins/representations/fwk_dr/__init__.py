"""Representation ``dr``: the deformation representation (thesis 2.1.4, 3.3.8, 4.4.1; Gao et
al. 2019 in the simplified form of Wu et al. 2018). 9 channels per vertex.

Encoding a mesh P' against a reference P (the training mean, or a per-sample reference such as
a subject's own neutral): for every vertex i, the deformation gradient T_i minimises

    E_i(T) = sum_{j in N(i)} c_ij || e'_ij - T e_ij ||^2  +  lam_i || T n_i - s_i n'_i ||^2
             + mu_i || T - sbar_i Rbar_i ||_F^2

with e_ij = p_i - p_j (reference), e'_ij the deformed edge, n_i, n'_i unit vertex normals.

- c_ij are the cotangent weights (cot a_ij + cot b_ij) / 2 of the fitted reference (eq. 2.5),
  clamped to [``weight_floor`` x their mean |c|, ``weight_ceiling``]: no weight is negative, and
  none exceeds ``weight_ceiling`` (10 = cot 5.7 deg, so only triangles with an angle below ~6 deg
  are affected; ICT-FaceKit's largest weight is 11.6, its 99.9th percentile 6.3). Unbounded, a
  needle's weight (cot of its tiny angle) amplifies noise on its short edge without limit.
- The normal term (lam_i = ``normal_weight`` x the mean c |e|^2 of the one-ring, s_i =
  sqrt(sum c |e'|^2 / sum c |e|^2) the local scale) guards flat one-rings, whose edges span only
  a plane, so T_i never collapses along the normal.
- The Tikhonov term (issue 17) guards one-rings that are tiny or collapsed. With kappa_i =
  sum_j c_ij |e_ij|^2 (a one-ring's energy per unit stretch, proportional to its area) and
  kappa~ its median over the fitted mean's vertices, its weight is mu_i = (tau kappa~)^2 / kappa_i,
  tau = ``regularisation``: relative to the one-ring's own energy it is (tau kappa~ / kappa_i)^2,
  so it takes over below tau times the typical energy and vanishes quadratically above. Its
  target is the similarity of the closed neighbourhood Nbar(i) = {i} u N(i): Rbar_i =
  polar(sum_{k in Nbar(i)} B_k) (rotation part, det +1) and sbar_i^2 = sum_{k in Nbar(i)} sum_j
  c_kj |e'_kj|^2 / sum_{k in Nbar(i)} kappa_k.

Closed form. With A_i = sum c e e^T + lam n n^T and B_i = sum c e' e^T + lam s n' n^T,

    T_i = (B_i + mu_i sbar_i Rbar_i) (A_i + mu_i I)^-1.

Why this regulariser (the math):

- *Exact for similarities*, for every tau: if P' = s Q P + t then e' = s Q e, n' = Q n,
  s_i = s, so B_k = s Q A_k for every k, Rbar_i = polar(s Q sum A_k) = Q (the sum is positive
  definite), sbar_i = s, and T_i = s Q (A_i + mu_i I)(A_i + mu_i I)^-1 = s Q. The reference
  itself encodes to 0.
- *Vanishes where the one-ring is well shaped*: T_i - T_i^0 = mu_i (sbar Rbar - T_i^0)(A_i +
  mu_i I)^-1 with T_i^0 = B_i A_i^-1 the unregularised gradient, so the change is at most
  mu_i / lambda_min(A_i) of T_i^0's deviation from the neighbourhood's similarity. For a
  one-ring of typical size lambda_min(A_i) ~ kappa_i / 60 (the normal direction, with the default
  normal_weight and six neighbours), so with tau = 0.01 the bound is 60 tau^2 = 0.6 %; on
  synthetic heads under random smooth deformations the rotations move by 0.35-0.54 % of the
  deformation's largest local rotation (tested against a naive solve of the unregularised
  energy: under 1 %).
- *Bounded sensitivity*: a displacement of the deformed vertices by at most delta changes B_i by
  ||dB_i|| <= 2 delta sqrt(C_i kappa_i) (Cauchy-Schwarz, C_i = sum_j c_ij <= degree x
  weight_ceiling; plus the normal term, smaller by normal_weight), and
  lambda_min(A_i + mu_i I) >= max(lambda_min(A_i), mu_i), so ||dT_i|| <= 2 delta sqrt(C_i kappa_i)
  / max(lambda_min(A_i), (tau kappa~)^2 / kappa_i), which tends to 0 with kappa_i: the smaller
  the one-ring, the more firmly it follows its neighbourhood. Unregularised, a one-ring of size h
  moves by delta / h: at a collapsed one-ring (every neighbour within 1e-4 of an edge of the
  vertex) noise of 1e-3 of an edge gave |log R| up to 3.10 rad and |S - I| up to 77; regularised
  0.008 and 0.012, as at a well-shaped one-ring (tests/representations/test_dr_degenerate.py;
  the needle's 1e7 weight gave |S - I| 0.76, clamped 0.011).
- *Tiny one-rings follow their neighbourhood*: where kappa_i << tau kappa~, T_i -> sbar_i Rbar_i,
  the similarity of the surrounding triangles, a proper rotation: a sliver that folds (a
  reflection, det T < 0, whose rotation part is near pi) gives a bounded rotation.

``regularisation: 0`` and ``weight_ceiling: null`` give the earlier behaviour exactly (what a
state saved before issue 17 loads as). On ICT-FaceKit the folds are in the data (triangles whose
normal reverses between a mesh and its reference); the default tau = 0.01 removes 96 % of the
identities' rotations above 2 rad and two thirds of the (sample, vertex) folds of identities and
expressions, for a round trip 5 % (identities) and 52 % (expressions) less accurate: the figures,
and the other values measured, are in docs/methods/spectral.md ("measured on ICT-FaceKit").

Polar decomposition T = R S (det R = +1; scaled Newton, SVD where det T <= 0); features are
log R as an axis-angle 3-vector and the upper triangle of S - I (6 numbers), scaled by
``scaling`` (none / std / norm, with ``granularity``, ``range``, ``q`` and ``centre`` as in
``fwk.scaling``).

Decoding: T_i = exp(r_i) (I + S_i), then the Poisson-type system (Wu et al. 2018)

    sum_j c_ij ((p'_i - p'_j) - (T_i + T_j)/2 e_ij) = 0   for every i

i.e. L_c p' = b with the template's weighted graph Laplacian L_c (the same clamped weights),
factorised once (SuperLU) with one vertex per connected component pinned; all meshes and
coordinates are solved as one block. The factorisation is kept in memory, keyed by the content
hash of the reference geometry, topology and weight clamps, so every DR instance on the same
template shares it.

DR does not encode position (nor, for the whole mesh, orientation), so a decoded mesh is
placed by rigid registration (Kabsch, no scaling): with ``target`` given to ``decode`` (the
ground truth), onto the target, the thesis's evaluation protocol for DR outputs; without one
(generation), onto the reference. ``align="target"`` makes the target mandatory (an
evaluation that must never silently fall back to the reference).

``ref="mean"``: the reference is the fitted training mean unless ``encode``/``decode`` get a
per-sample ``ref`` (b, n, 3) or (n, 3); ``ref="sample"`` requires one (a subject's own neutral
for expressions, thesis 5.2) and fails clearly without it. The cotangent weights, mu (and the
factorisation) always come from the fitted mean, so per-sample references cost nothing extra.

Scaling defaults (issue 17, measured on ICT-FaceKit, docs/methods/spectral.md): norm per vertex
and channel, over the 1-99 % quantile range, centred on the training mean, so a zero network
output decodes to the mean features; ``scaling: std`` is per vertex and channel as before.

Guards (never NaN): a flat one-ring is held by the normal term; an isolated vertex (no edge) gets
T = I and is pinned to the reference when decoding.

Round trip: similarity transforms of the reference come back exactly (to 1e-10, tested);
a smooth general deformation comes back to within 1 % of its largest displacement (tested; the
least-squares gradients of a non-affine deformation are not integrable exactly).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from fwk.cache import content_key, memo, memo_each
from fwk.errors import DataError, RecipeError
from fwk.geometry import kabsch
from fwk.geometry.operators import cotangent_laplacian
from fwk.hookspecs import hookimpl
from fwk.scaling import Scaler

ALIGN = ("reference", "target")
REFS = ("mean", "sample")
#: the samples encoded or decoded at once are chosen so that the largest intermediate, the
#: per-half-edge terms (chunk, halfedges, 10) in float64, stays under this many bytes: all at once,
#: 1,368 ICT-FaceKit meshes (11,248 vertices) took over 22 GB and were killed for memory
CHUNK_BYTES = 256 * 2**20
#: ``raw_features`` remembers the features of the meshes it computed last, at most MEMO_BYTES of them
MEMO_BYTES = 512 * 2**20


def _rows(a, i: int, j: int, b: int):
    """Samples i:j of ``a`` when it has one row per sample (b rows), else ``a`` (None, or shared)."""
    return a[i:j] if a is not None and np.ndim(a) == 3 and len(a) == b > 1 else a


def _cross_into(out, a, b):
    """out[..., :] = a x b for (..., 3) arrays (np.cross is several times slower on small rows)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _cross(a, b):
    return _cross_into(np.empty(np.broadcast_shapes(a.shape, b.shape)), a, b)


def _cofactor_rows(x: list) -> list:
    """The 9 components of the cofactor matrix (row-major) of the matrix whose row-major components
    are the arrays x[0..8]: rows x1 x x2, x2 x x0, x0 x x1."""
    out = []
    for a, b in ((1, 2), (2, 0), (0, 1)):
        a0, a1, a2 = x[3 * a], x[3 * a + 1], x[3 * a + 2]
        b0, b1, b2 = x[3 * b], x[3 * b + 1], x[3 * b + 2]
        out += [a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0]
    return out


def polar(T, iters: int = 30, tol: float = 1e-14):
    """T = R S with R a rotation and S symmetric: scaled Newton iteration (Higham 1986),
    X <- (g X + X^-T / g) / 2, g = |det X|^(-1/3), X^-T = cof(X) / det X, vectorised over
    (..., 3, 3); vertices whose T has det <= 0 (a reflection, or degenerate) use the SVD with
    det R = +1. The iteration runs on the nine components as contiguous arrays (one pass each
    per operation; on (..., 3, 3) slices every operation strode over the matrices: 1.7-2.8x slower
    at 243,200 matrices, ``benchmarks/pipeline.py``)."""
    shape = T.shape
    x = list(np.ascontiguousarray(T.reshape(-1, 9).T))
    c = _cofactor_rows(x)
    det = x[0] * c[0] + x[1] * c[1] + x[2] * c[2]
    bad = det <= 1e-300
    if bad.any():
        for k in range(9):
            x[k] = np.where(bad, 1.0 if k in (0, 4, 8) else 0.0, x[k])
        c = _cofactor_rows(x)
        det = x[0] * c[0] + x[1] * c[1] + x[2] * c[2]
    for _ in range(iters):  # c, det: the cofactors and determinant of the current x
        g = np.abs(det) ** (-1.0 / 3.0)
        gd = g * det
        xn = [0.5 * (g * x[k] + c[k] / gd) for k in range(9)]
        done = max(float(np.abs(xn[k] - x[k]).max(initial=0.0)) for k in range(9)) < tol
        x = xn
        if done:
            break
        c = _cofactor_rows(x)
        det = x[0] * c[0] + x[1] * c[1] + x[2] * c[2]
    R = np.stack(x, axis=-1).reshape(shape)
    bad = bad.reshape(shape[:-2])
    if bad.any():
        U, sig, Vt = np.linalg.svd(T[bad])
        d = np.sign(np.linalg.det(U @ Vt))
        d[d == 0] = 1
        U[..., :, 2] *= d[..., None]
        R[bad] = U @ Vt
    S = np.einsum("...ji,...jk->...ik", R, T)
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    return R, S


def _operators(mean: np.ndarray, F: np.ndarray, weight_floor: float, weight_ceiling: float | None) -> dict:
    """What depends on the fitted mean only: the clamped cotangent weights of the directed
    half-edges, the vertex incidence, the factorised weighted Laplacian with one pin per
    connected component, the vertex-face incidence, the vertex degrees, the closed-neighbourhood
    matrix K = adjacency + I and the median one-ring energy kappa (non-isolated vertices)."""
    n = len(mean)
    L = cotangent_laplacian(mean, F).tocoo()
    off = L.row < L.col
    i, j, c = L.row[off], L.col[off], -L.data[off]
    floor = weight_floor * np.abs(c).mean()
    c = np.maximum(c, floor)
    if weight_ceiling is not None:
        c = np.minimum(c, weight_ceiling)
    # directed half-edges (i -> j) both ways
    hi = np.concatenate([i, j])
    hj = np.concatenate([j, i])
    hc = np.concatenate([c, c])
    inc = sp.csr_matrix((np.ones(len(hi)), (hi, np.arange(len(hi)))), shape=(n, len(hi)))
    W = sp.coo_matrix((hc, (hi, hj)), shape=(n, n)).tocsr()
    Lc = (sp.diags(np.asarray(W.sum(1)).ravel()) - W).tolil()
    _, labels = connected_components(W, directed=False)
    pins = np.array([np.flatnonzero(labels == k)[0] for k in range(labels.max() + 1)])
    for p in pins:
        Lc.rows[p] = [p]
        Lc.data[p] = [1.0]
    lu = splu(Lc.tocsc(), permc_spec="COLAMD")
    m = len(F)
    vf = sp.csr_matrix((np.ones(3 * m), (F.ravel(), np.repeat(np.arange(m), 3))), shape=(n, m))
    deg = np.maximum(np.asarray(inc.sum(1)).ravel(), 1)
    K = (sp.csr_matrix((np.ones(len(hi)), (hi, hj)), shape=(n, n)) + sp.identity(n, format="csr")).tocsr()
    K.data[:] = 1.0
    e = mean[hi] - mean[hj]
    kappa = inc @ (hc * (e * e).sum(-1))
    live = kappa > 0
    kappa_typ = float(np.median(kappa[live])) if live.any() else 0.0
    return {"hi": hi, "hj": hj, "hc": hc, "inc": inc, "lu": lu, "pins": pins, "vf": vf, "deg": deg, "K": K,
            "kappa_typ": kappa_typ}


class DR:
    """Deformation representation: per-vertex log-rotation and stretch (9 channels)."""

    name = "dr"
    channels = 9
    places_rigidly = True  # decode integrates up to a rigid motion: placed onto `target` when given
    relative_option = False  # always the deformation from ref
    relative = True
    scaler: Scaler | None = None  # each instance sets its own: the scaling encode applies last

    def __init__(self, scaling: str = "norm", granularity: str | None = "vertex", a: float = 1.0, ref: str = "mean",
                 align: str = "reference", normal_weight: float = 0.1, weight_floor: float = 1e-3,
                 eps: float = 1e-8, range: str = "quantile", q: float = 0.01, centre: str = "mean",
                 regularisation: float = 1e-2, weight_ceiling: float | None = 10.0):
        if align not in ALIGN:
            raise RecipeError(f"align: expected one of {', '.join(ALIGN)}, got {align!r}")
        if ref not in REFS:
            raise RecipeError(f"ref: expected one of {', '.join(REFS)}, got {ref!r}")
        if not regularisation >= 0:
            raise RecipeError(f"regularisation: expected a number >= 0, got {regularisation!r}")
        if weight_ceiling is not None and not weight_ceiling > 0:
            raise RecipeError(f"weight_ceiling: expected a number > 0 or null, got {weight_ceiling!r}")
        self.scaler = Scaler(scaling, granularity, a, eps, range=range, q=q, centre=centre)
        self.ref_mode = ref
        self.align, self.normal_weight, self.weight_floor = align, normal_weight, weight_floor
        self.regularisation = float(regularisation)
        self.weight_ceiling = None if weight_ceiling is None else float(weight_ceiling)
        self.mean = self.F = None
        self._ops = self._mean_terms = None

    # ------------------------------------------------------------------ operators
    def _setup(self, mean, F):
        self._mean_terms = None
        self.mean = np.asarray(mean, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        key = content_key(self.mean, self.F, self.weight_floor, self.weight_ceiling)
        self._ops = memo(f"{__name__}.operators", key,
                         lambda: _operators(self.mean, self.F, self.weight_floor, self.weight_ceiling), size=8)

    def _mu(self, den):
        """The Tikhonov weights mu_i = (tau kappa~)^2 / kappa_i for one-ring energies den (r, n)
        (tau = ``regularisation``, kappa~ the fitted mean's median one-ring energy)."""
        m = self.regularisation * self._ops["kappa_typ"]
        return m * m / (den + 1e-12 * m)

    def _ref_terms(self, ref):
        """What depends on the reference only: its edges e (r, h, 3), normals n0, the one-ring
        sums den = kappa = sum c |e|^2 (and their neighbourhood sums Kden when mu > 0), the guard
        weight lam and the inverse of A + mu I, A = sum c e e^T + lam n0 n0^T (r, n, 3, 3); r = 1
        for the fitted mean (cached)."""
        if ref is None and self._mean_terms is not None:
            return self._mean_terms
        o = self._ops
        R0 = self.mean[None] if ref is None else ref
        e = R0[:, o["hi"]] - R0[:, o["hj"]]
        c = o["hc"][None, :, None]
        ce = c * e
        G = np.concatenate([(ce[..., :, None] * e[..., None, :]).reshape(len(R0), -1, 9),
                            (ce * e).sum(-1, keepdims=True)], axis=-1)
        S = np.stack([o["inc"] @ G[s] for s in range(len(R0))])  # one sparse sum onto the vertices
        A = S[..., :9].reshape(len(R0), -1, 3, 3)
        den = S[..., 9]
        lam = self.normal_weight * den / o["deg"]
        n0 = self._normals(R0)
        A = A + lam[..., None, None] * n0[..., :, None] * n0[..., None, :]
        mu = self._mu(den) if self.regularisation > 0 else None
        if mu is not None:
            A = A + mu[..., None, None] * np.eye(3)
        # guard: a vertex with no (non-degenerate) edge has no gradient: T = I there
        iso = ~(den > 1e-300 * max(float(np.abs(den).max(initial=0.0)), 1e-300))
        A[iso] = np.eye(3)
        terms = {"e": e, "n0": n0, "den": den, "lam": lam, "Ainv": np.linalg.inv(A), "iso": iso}
        if mu is not None:
            terms["mu"] = mu
            terms["Kden"] = np.stack([o["K"] @ den[s] for s in range(len(R0))])
        if ref is None:
            self._mean_terms = terms
        return terms

    def _gradients_of(self, P, ref):
        """T (b, n, 3, 3) = (B + mu sbar Rbar)(A + mu I)^-1, the guarded cotangent-weighted
        least-squares gradients (module docstring)."""
        o = self._ops
        b, n = P.shape[:2]
        t = self._ref_terms(ref)
        e = t["e"]
        ed = P[:, o["hi"]] - P[:, o["hj"]]
        c = o["hc"][None, :, None]
        G = np.concatenate([(c[..., None] * ed[..., :, None] * e[..., None, :]).reshape(b, -1, 9),
                            (c * ed * ed).sum(-1, keepdims=True)], axis=-1)
        S = np.stack([o["inc"] @ G[s] for s in range(b)])  # (b, n, 10)
        B = S[..., :9].reshape(b, -1, 3, 3)
        s = np.sqrt(S[..., 9] / np.maximum(t["den"], 1e-300))
        n1 = self._normals(P)
        B = B + (t["lam"] * s)[..., None, None] * n1[..., :, None] * t["n0"][..., None, :]
        if self.regularisation > 0:  # the similarity of the closed neighbourhood: Rbar = polar(K B), sbar^2 = K E' / K kappa
            K = o["K"]
            KB = np.stack([K @ B[q].reshape(n, 9) for q in range(b)]).reshape(b, n, 3, 3)
            KE = np.stack([K @ S[q, :, 9] for q in range(b)])
            sbar = np.sqrt(KE / np.maximum(t["Kden"], 1e-300))
            Rbar, _ = polar(KB)
            B = B + (t["mu"] * sbar)[..., None, None] * Rbar
        B[np.broadcast_to(t["iso"], B.shape[:2])] = np.eye(3)
        return B @ t["Ainv"]

    def _normals(self, V):
        F = self.F
        N = _cross(V[:, F[:, 1]] - V[:, F[:, 0]], V[:, F[:, 2]] - V[:, F[:, 0]])
        out = np.stack([self._ops["vf"] @ N[s] for s in range(len(V))])
        nrm = np.linalg.norm(out, axis=-1, keepdims=True)
        return out / np.where(nrm > 0, nrm, 1.0)

    def _refs(self, ref, b):
        if self._ops is None:
            raise RuntimeError("dr representation used before fit()")
        if ref is None and self.ref_mode == "sample":
            raise RecipeError("ref: this dr representation has ref: sample, so encode/decode need a per-sample "
                              "reference (e.g. each subject's neutral)")
        if ref is None:
            return np.broadcast_to(self.mean, (b, *self.mean.shape))
        r = np.asarray(ref, dtype=np.float64)
        return np.broadcast_to(r, (b, *self.mean.shape)) if r.ndim == 2 else r

    # ------------------------------------------------------------------ features
    def raw_features(self, P, ref=None) -> np.ndarray:
        """(b, n, 9) unscaled features [log R | upper triangle of S - I] of P against ``ref``.

        Remembered mesh by mesh (``fwk.cache.memo_each``, at most ``MEMO_BYTES`` in all, keyed by
        the content of the mesh, its reference, the fitted mean and every parameter the features
        depend on): ``fit`` then ``encode`` of the same meshes compute them once, also when they
        come in other batches. PB's expression networks fit on every expression's meshes at once
        and encode them expression by expression: with one result per call remembered, the main
        job computed them twice (16 of each PBS process's 40 s of DR features). A mesh's features
        do not depend on the others of its batch except through the polar decomposition's
        stopping test (the batch iterates until its slowest matrix converges, to 1e-14): a
        remembered mesh may differ from one computed in another batch by that much. Each call
        returns its own copy."""
        P = np.asarray(P, dtype=np.float64)
        single = P.ndim == 2
        P = P[None] if single else P
        self._refs(ref, len(P))  # checks
        r = None if ref is None else np.asarray(ref, dtype=np.float64)
        if r is not None and r.ndim == 2:
            r = r[None]
        fitted = content_key(self.mean, self.F, self.normal_weight, self.weight_floor, self.weight_ceiling,
                             self.regularisation)
        keys = [content_key(fitted, P[s], None if r is None else r[s if len(r) > 1 else 0]) for s in range(len(P))]

        def build(missing):  # the meshes not remembered, in one batch
            return list(self._raw_features(P[missing], r if r is None or len(r) == 1 else r[missing]))

        F = np.stack(memo_each(f"{__name__}.raw_features", keys, build, MEMO_BYTES))
        return F[0] if single else F

    def _raw_features(self, P, r) -> np.ndarray:
        """``raw_features`` of (b, n, 3) P against r (None, or (1 or b, n, 3)), not remembered."""
        step, b = self._chunk(), len(P)
        if b > step:  # same values, bounded memory (CHUNK_BYTES)
            return np.concatenate([self._raw_features(P[i:i + step], _rows(r, i, i + step, b))
                                   for i in range(0, b, step)])
        T = self._gradients_of(P, r)
        Rm, S = polar(T)
        rv = Rotation.from_matrix(Rm.reshape(-1, 3, 3)).as_rotvec().reshape(*Rm.shape[:2], 3)
        iu = np.triu_indices(3)
        Sm = S - np.eye(3)
        return np.concatenate([rv, Sm[..., iu[0], iu[1]]], axis=-1)

    def gradients(self, F) -> np.ndarray:
        """(..., 9) unscaled features -> (..., 3, 3) T = exp(log R) (I + (S - I))."""
        F = np.asarray(F, dtype=np.float64)
        rv, su = F[..., :3], F[..., 3:]
        R = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(*rv.shape[:-1], 3, 3)
        S = np.zeros((*su.shape[:-1], 3, 3))
        iu = np.triu_indices(3)
        S[..., iu[0], iu[1]] = su
        S[..., iu[1], iu[0]] = su
        S += np.eye(3)
        return R @ S

    def integrate(self, T, ref=None, target=None) -> np.ndarray:
        """Positions (b, n, 3) whose edges best follow the gradients T (b, n, 3, 3), placed
        rigidly onto ``target`` (or the reference)."""
        o = self._ops
        b = len(T)
        R0 = self._refs(ref, b)
        e = R0[:, o["hi"]] - R0[:, o["hj"]]
        Tm = 0.5 * (T[:, o["hi"]] + T[:, o["hj"]])
        g = o["hc"][None, :, None] * np.einsum("bhij,bhj->bhi", Tm, e)  # (b, h, 3)
        rhs = np.stack([o["inc"] @ g[s] for s in range(b)])  # (b, n, 3)
        rhs[:, o["pins"]] = R0[:, o["pins"]]
        cols = rhs.transpose(1, 0, 2).reshape(rhs.shape[1], -1)
        X = o["lu"].solve(cols).reshape(rhs.shape[1], b, 3).transpose(1, 0, 2)
        if target is None and self.align == "target":
            raise RecipeError("align: this dr representation has align: target, so decode needs the ground truth "
                              "as target")
        goal = R0 if target is None else np.asarray(target, dtype=np.float64).reshape(X.shape)
        R, t = kabsch(X, goal)
        return np.einsum("bij,bnj->bni", R, X) + t[:, None]

    # ------------------------------------------------------------------ protocol
    def fit(self, P, ref=None, template=None) -> None:
        P = np.asarray(P, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (template.n_vertices, 3):
            raise DataError(f"dr.fit: expected meshes of shape (b, {template.n_vertices}, 3), got {P.shape}")
        if ref is None and self.ref_mode == "sample":
            raise RecipeError("ref: this dr representation has ref: sample, so fit needs the per-sample references")
        r = None if ref is None else np.asarray(ref, dtype=np.float64)
        self._setup(P.mean(axis=0) if r is None else (r.mean(axis=0) if r.ndim == 3 else r), template.triangles)
        self.scaler.fit(self.raw_features(P, ref))

    def encode(self, P, ref=None) -> np.ndarray:
        return self.scaler.transform(self.raw_features(P, ref)).astype(np.float32)

    def decode(self, F, ref=None, target=None) -> np.ndarray:
        F = np.asarray(F, dtype=np.float64)
        single = F.ndim == 2
        F = F[None] if single else F
        step, b = self._chunk(), len(F)
        if b > step:  # same values, bounded memory (CHUNK_BYTES)
            t = None if target is None else np.asarray(target, dtype=np.float64).reshape(F.shape[:2] + (3,))
            return np.concatenate([self.decode(F[i:i + step], _rows(ref, i, i + step, b), _rows(t, i, i + step, b))
                                   for i in range(0, b, step)])
        X = self.integrate(self.gradients(self.scaler.inverse(F)), ref, target)
        return X[0] if single else X

    def _chunk(self) -> int:
        """How many samples to encode or decode at once (``CHUNK_BYTES``)."""
        if self._ops is None:
            raise RuntimeError("dr representation used before fit()")
        return max(1, CHUNK_BYTES // (len(self._ops["hi"]) * 10 * 8))

    def unscale(self, F):
        return self.scaler.inverse_torch(F)

    def state_dict(self) -> dict:
        return {"scaler": self.scaler.state_dict(), "mean": self.mean, "F": self.F, "align": self.align,
                "ref": self.ref_mode, "normal_weight": self.normal_weight, "weight_floor": self.weight_floor,
                "regularisation": self.regularisation, "weight_ceiling": self.weight_ceiling}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore ``state_dict``'s output. A state saved before issue 17 has no ``regularisation``
        or ``weight_ceiling``: it loads with neither (0, no ceiling), the features it was trained on."""
        self.scaler.load_state_dict(d["scaler"])
        self.align, self.normal_weight = str(d["align"]), float(d["normal_weight"])
        self.ref_mode = str(d.get("ref", "mean"))
        self.weight_floor = float(d["weight_floor"])
        self.regularisation = float(d.get("regularisation", 0.0))
        wc = d.get("weight_ceiling")
        self.weight_ceiling = None if wc is None else float(wc)
        self._mean_terms = None
        self._setup(np.asarray(d["mean"]), np.asarray(d["F"]))


@hookimpl
def fwk_register_representations():
    return [DR]
