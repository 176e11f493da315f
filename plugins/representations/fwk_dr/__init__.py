"""Representation ``dr``: the deformation representation (thesis 2.1.4, 3.3.8, 4.4.1; Gao et
al. 2019 in the simplified form of Wu et al. 2018). 9 channels per vertex.

Encoding a mesh P' against a reference P (the training mean, or a per-sample reference such as
a subject's own neutral): for every vertex i, the deformation gradient T_i minimises

    sum_{j in N(i)} c_ij || e'_ij - T_i e_ij ||^2  +  lam_i || T_i n_i - s_i n'_i ||^2

with e_ij = p_i - p_j (reference), e'_ij the deformed edge, c_ij the cotangent weights of the
fitted template (clamped below at ``weight_floor`` x their mean so that no weight is negative),
n_i, n'_i unit vertex normals and s_i = sqrt(sum c |e'|^2 / sum c |e|^2) the local scale. The
normal term (weight lam_i = ``normal_weight`` x the mean c |e|^2 of the one-ring) guards flat
one-rings, whose edges span only a plane, so T_i (and S) never collapse; with s_i it is exact
for similarity transforms. Closed form: T_i = (sum c e' e^T + lam s n' n^T)(sum c e e^T + lam n n^T)^-1.
Polar decomposition T = R S (SVD, det R = +1); features are log R as an axis-angle 3-vector
and the upper triangle of S - I (6 numbers), scaled by ``scaling`` (none / std / norm).

Decoding: T_i = exp(r_i) (I + S_i), then the Poisson-type system (Wu et al. 2018)

    sum_j c_ij ((p'_i - p'_j) - (T_i + T_j)/2 e_ij) = 0   for every i

i.e. L_c p' = b with the template's weighted graph Laplacian L_c, factorised once (SuperLU) with
one vertex per connected component pinned; all meshes and coordinates are solved as one block.
The factorisation is kept in memory, keyed by the content hash of the reference geometry and
topology, so every DR instance on the same template shares it.

DR does not encode position (nor, for the whole mesh, orientation), so a decoded mesh is
placed by rigid registration (Kabsch, no scaling): with ``target`` given to ``decode`` (the
ground truth), onto the target, the thesis's evaluation protocol for DR outputs; without one
(generation), onto the reference. ``align="target"`` makes the target mandatory (an
evaluation that must never silently fall back to the reference).

``ref="mean"``: the reference is the fitted training mean unless ``encode``/``decode`` get a
per-sample ``ref`` (b, n, 3) or (n, 3); ``ref="sample"`` requires one (a subject's own neutral
for expressions, thesis 5.2) and fails clearly without it. The cotangent weights (and the
factorisation) always come from the fitted mean, so per-sample references cost nothing extra.

Guards (never NaN): a flat one-ring is held by the normal term; an isolated vertex (no edge) gets
T = I and is pinned to the reference when decoding.

Round trip: similarity transforms of the reference come back exactly (to 1e-10, tested);
a smooth general deformation comes back to within 1e-3 of the mesh size (tested; the
least-squares gradients of a non-affine deformation are not integrable exactly).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from fwk.cache import content_key, memo
from fwk.errors import DataError, RecipeError
from fwk.geometry import kabsch
from fwk.geometry.operators import cotangent_laplacian
from fwk.hookspecs import hookimpl
from fwk.scaling import Scaler

ALIGN = ("reference", "target")
REFS = ("mean", "sample")


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


def _cofactor(X):
    c = np.empty_like(X)
    _cross_into(c[..., 0, :], X[..., 1, :], X[..., 2, :])
    _cross_into(c[..., 1, :], X[..., 2, :], X[..., 0, :])
    _cross_into(c[..., 2, :], X[..., 0, :], X[..., 1, :])
    return c


def polar(T, iters: int = 30, tol: float = 1e-14):
    """T = R S with R a rotation and S symmetric: scaled Newton iteration (Higham 1986),
    X <- (g X + X^-T / g) / 2, g = |det X|^(-1/3), vectorised over (..., 3, 3); vertices whose
    T has det <= 0 (a reflection, or degenerate) use the SVD with det R = +1."""
    X = T.copy()
    det = np.einsum("...i,...i->...", X[..., 0, :], _cofactor(X)[..., 0, :])
    bad = det <= 1e-300
    X[bad] = np.eye(3)
    for _ in range(iters):
        cof = _cofactor(X)
        det = np.einsum("...i,...i->...", X[..., 0, :], cof[..., 0, :])
        g = np.abs(det) ** (-1.0 / 3.0)
        Xn = 0.5 * (g[..., None, None] * X + cof / (g * det)[..., None, None])
        done = np.abs(Xn - X).max() < tol
        X = Xn
        if done:
            break
    R = X
    if bad.any():
        U, sig, Vt = np.linalg.svd(T[bad])
        d = np.sign(np.linalg.det(U @ Vt))
        d[d == 0] = 1
        U[..., :, 2] *= d[..., None]
        R[bad] = U @ Vt
    S = np.einsum("...ji,...jk->...ik", R, T)
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    return R, S


def _operators(mean: np.ndarray, F: np.ndarray, weight_floor: float) -> dict:
    """What depends on the fitted mean only: the floored cotangent weights of the directed
    half-edges, the vertex incidence, the factorised weighted Laplacian with one pin per
    connected component, the vertex-face incidence and the vertex degrees."""
    n = len(mean)
    L = cotangent_laplacian(mean, F).tocoo()
    off = L.row < L.col
    i, j, c = L.row[off], L.col[off], -L.data[off]
    floor = weight_floor * np.abs(c).mean()
    c = np.maximum(c, floor)
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
    return {"hi": hi, "hj": hj, "hc": hc, "inc": inc, "lu": lu, "pins": pins, "vf": vf, "deg": deg}


class DR:
    """Deformation representation: per-vertex log-rotation and stretch (9 channels)."""

    name = "dr"
    channels = 9
    places_rigidly = True  # decode integrates up to a rigid motion: placed onto `target` when given
    relative_option = False  # always the deformation from ref
    relative = True

    def __init__(self, scaling: str = "norm", granularity: str = "vertex", a: float = 1.0, ref: str = "mean",
                 align: str = "reference", normal_weight: float = 0.1, weight_floor: float = 1e-3,
                 eps: float = 1e-8):
        if align not in ALIGN:
            raise RecipeError(f"align: expected one of {', '.join(ALIGN)}, got {align!r}")
        if ref not in REFS:
            raise RecipeError(f"ref: expected one of {', '.join(REFS)}, got {ref!r}")
        self.scaler = Scaler(scaling, granularity, a, eps)
        self.ref_mode = ref
        self.align, self.normal_weight, self.weight_floor = align, normal_weight, weight_floor
        self.mean = self.F = None
        self._ops = self._mean_terms = None

    # ------------------------------------------------------------------ operators
    def _setup(self, mean, F):
        self._mean_terms = None
        self.mean = np.asarray(mean, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        self._ops = memo(f"{__name__}.operators", content_key(self.mean, self.F, self.weight_floor),
                         lambda: _operators(self.mean, self.F, self.weight_floor), size=8)

    def _ref_terms(self, ref):
        """What depends on the reference only: its edges e (r, h, 3), normals n0, the one-ring
        sums den = sum c |e|^2, the guard weight lam and the inverse of
        A = sum c e e^T + lam n0 n0^T (r, n, 3, 3); r = 1 for the fitted mean (cached)."""
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
        # guard: a vertex with no (non-degenerate) edge has no gradient: T = I there
        iso = ~(den > 1e-300 * max(float(np.abs(den).max(initial=0.0)), 1e-300))
        A[iso] = np.eye(3)
        terms = {"e": e, "n0": n0, "den": den, "lam": lam, "Ainv": np.linalg.inv(A), "iso": iso}
        if ref is None:
            self._mean_terms = terms
        return terms

    def _gradients_of(self, P, ref):
        """T (b, n, 3, 3) = B A^-1, the guarded cotangent-weighted least-squares gradients."""
        o = self._ops
        b = len(P)
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
        P = np.asarray(P, dtype=np.float64)
        single = P.ndim == 2
        P = P[None] if single else P
        self._refs(ref, len(P))  # checks
        r = None if ref is None else np.asarray(ref, dtype=np.float64)
        if r is not None and r.ndim == 2:
            r = r[None]
        T = self._gradients_of(P, r)
        Rm, S = polar(T)
        rv = Rotation.from_matrix(Rm.reshape(-1, 3, 3)).as_rotvec().reshape(*Rm.shape[:2], 3)
        iu = np.triu_indices(3)
        Sm = S - np.eye(3)
        F = np.concatenate([rv, Sm[..., iu[0], iu[1]]], axis=-1)
        return F[0] if single else F

    def gradients(self, F) -> np.ndarray:
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
        X = self.integrate(self.gradients(self.scaler.inverse(F)), ref, target)
        return X[0] if single else X

    def unscale(self, F):
        return self.scaler.inverse_torch(F)

    def state_dict(self) -> dict:
        return {"scaler": self.scaler.state_dict(), "mean": self.mean, "F": self.F, "align": self.align,
                "ref": self.ref_mode, "normal_weight": self.normal_weight, "weight_floor": self.weight_floor}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        self.scaler.load_state_dict(d["scaler"])
        self.align, self.normal_weight = str(d["align"]), float(d["normal_weight"])
        self.ref_mode = str(d.get("ref", "mean"))
        self.weight_floor = float(d["weight_floor"])
        self._mean_terms = None
        self._setup(np.asarray(d["mean"]), np.asarray(d["F"]))


@hookimpl
def fwk_register_representations():
    return [DR]
