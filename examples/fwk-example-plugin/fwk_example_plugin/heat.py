r"""An example third-party assembler: frequency bands by heat diffusion on the template, the
implicit smoothing of Desbrun, Meyer, Schroeder and Barr 1999 ("Implicit Fairing of Irregular
Meshes using Diffusion and Curvature Flow", SIGGRAPH), in place of ``spectral``'s eigenvectors.

Operators (``fwk.geometry.operators``, on the fitted mean's geometry, as ``spectral``): L the
cotangent Laplacian (positive semi-definite, rows summing to zero), M the lumped (mixed Voronoi)
mass matrix; ``mass: false`` takes M = I. One implicit (backward Euler) step of the heat equation
dP/dt = Delta P, with the discrete Laplace-Beltrami operator Delta = -M^{-1} L, over a time tau is
Desbrun et al.'s implicit fairing (I - tau Delta) P_low = P, multiplied through by M:

    (M + tau L) P_low = M P,        i.e.   P_low = H_tau P,   H_tau = (M + tau L)^{-1} M,

factorised once per tau (SuperLU, ``scipy.sparse.linalg.splu``) at ``fit``. On the generalised
eigenvectors (L u = lambda M u) H_tau is the filter h(lambda) = 1 / (1 + tau lambda): it keeps
constants (lambda = 0, so a translation) whole, passes half of frequency lambda = 1 / tau and
damps higher ones, smoothly, without computing any eigenvector. It is M-self-adjoint with
response in (0, 1].

Bands. With cut filters F_1, ..., F_C ordered from the smoothest (largest tau) and F_0 = 0,
F_{C+1} = I, and D = P - P-bar (P-bar the ``mean`` given to ``fit``: dsm's training mean, pbs's
mean neutral; L and M are built on its geometry), band j is

    band_j(P) = (F_{j+1} - F_j) D + P-bar,          j = 0..C   (G_j = F_{j+1} - F_j),

so the bands' displacements sum to D exactly (the high band is D - F_C D) and every band is a
mesh centred on the mean (the mean splits into copies of itself), as ``spectral``'s. Each G_j is
a band-pass with response in [0, 1] (the h's decrease with tau) and the G_j's responses sum to 1
at every frequency; unlike ``spectral``'s projections the bands overlap (a frequency between two
cut points lies partly in both).

What a cut ``k`` means here. ``spectral``'s cut k keeps the k smallest eigenvectors in the low
band. Heat diffusion has no sharp cut; its nearest faithful meaning is the time whose filter
passes more than half of every eigenvector the spectral cut keeps and less than half of every
one it drops: the geometric midpoint between the k-th and (k+1)-th smallest eigenvalues
lambda_{k-1} <= lambda_k (0-based),

    tau_k = 1 / sqrt(lambda_{k-1} lambda_k),    h(lambda_{k-1}) >= 1/2 >= h(lambda_k),

with tau_k = infinity where lambda_{k-1} = 0 (then F is the M-orthogonal projection onto the
constants of each connected component, H_tau's limit: on a connected template k = 1 keeps
exactly what ``spectral``'s k = 1 keeps), F = I for k >= n (nothing above the cut) and F = 0 for
k = 0 (nothing below it). A multiplet of equal eigenvalues split by k is split evenly (h = 1/2
on all of it), where the spectral cut keeps an arbitrary part of it. The eigenvalues come from
fwk's ``eigenbasis`` (cached; it computes the vectors too, of which only the zero eigenvalues'
are kept), once at ``fit`` up to the last cut. ``t`` instead gives the diffusion times directly, with no
eigenvalues at all: tau = t tr(M) (a fraction of the surface area, of n with ``mass: false``), so
a recipe means the same at any scale; by Weyl's law lambda_k ~ 4 pi k / area, t ~ 1 / (4 pi k)
falls near cut k.

Assembly (``assemble``). Per-band reconstructions y_j = P'_j - P-bar (a model's band decoders)
are put back together by M-weighted least squares, the canonical dual of the split seen as a
frame: the D whose bands best match them,

    D = argmin sum_j ||G_j D - y_j||_M^2 = (sum_j G_j^2)^{-1} sum_j G_j y_j,    P' = D + P-bar,

solved by conjugate gradients in the M-inner product (sum_j G_j^2 is M-self-adjoint, with
response sum_j g_j^2 in [1/(C+1), 1]: condition number at most C + 1, a few iterations), started
from sum_j y_j (the exact answer when the y_j are a split, so ``assemble(split(P)) == P`` to
round-off). Per frequency, for two bands with h = F's response: D = (h y_0 + (1 - h) y_1) /
(h^2 + (1 - h)^2): the low band's reconstruction where h ~ 1, the high band's where h ~ 0, their
sum where each band holds half. For projections (``spectral``: G_j^2 = G_j, sum = I) this is
exactly eq. 4.15, P' = sum_j X_j (P'_j - P-bar) + P-bar: each band contributes only its own
frequencies; simply adding the bands up would let a band's errors at other frequencies (a
translation of the dr band) through.

``assemble_many([low, high], ks)`` (the PBS k sweep, eq. 5.10, whose sources are whole meshes,
not bands) blends F_k (low - high) + high for every cut k: the low frequencies of the first and
the rest of the second, the high source at k = 0, the low one at k >= n, one factorisation per
k. ``band_shares(D)`` is each band's share <G_j D, D>_M / ||D||_M^2 of a displacement's
M-weighted energy: non-negative, summing to 1, and for projections ||X_j D||_M^2 / ||D||_M^2,
``spectral``'s. Registered through this package's own entry point (``pyproject.toml``:
``[project.entry-points.fwk] example-heat = "fwk_example_plugin.heat"``).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from fwk.cache import default_cache
from fwk.errors import RecipeError
from fwk.geometry.operators import cotangent_laplacian, mass_matrix
from fwk.geometry.spectral import eigenbasis
from fwk.geometry.topology import connected_components
from fwk.hookspecs import hookimpl

DEFAULT_K = 500      # spectral's default cut, when neither k nor t is given
ZERO = 1e-8          # an eigenvalue below ZERO x the mean of diag(L) / diag(M) is a zero (a component's constant)
CG_RTOL = 1e-12      # assemble: the least-squares solve's relative residual (M-norm)
CG_MAXITER = 200
FILTERS_KEPT = 64    # assemble_many: factorisations of cut points kept between calls


class _LowPass:
    """One low-pass filter F (n x n, never formed) applied to (n, m) columns."""

    def __init__(self, kind: str, m: np.ndarray, L=None, tau: float | None = None, null: np.ndarray | None = None):
        self.kind, self.m, self.tau = kind, m, tau
        if kind == "heat":  # (M + tau L) X = M P, factorised once
            self.lu = splu(sp.csc_matrix(sp.diags(m) + tau * L))
        elif kind == "kernel":  # tau -> infinity: U0 U0^T M onto the constants of each component
            self.U0, self.U0tM = null, (null * m[:, None]).T
        elif kind not in ("zero", "identity"):
            raise ValueError(kind)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        if self.kind == "heat":
            return self.lu.solve(self.m[:, None] * X)
        if self.kind == "kernel":
            return self.U0 @ (self.U0tM @ X)
        return X.copy() if self.kind == "identity" else np.zeros_like(X)


def _columns(P: np.ndarray, n: int) -> tuple[np.ndarray, tuple]:
    """(..., n, 3) -> (n, 3b) columns and what ``_meshes`` needs to fold them back."""
    if P.ndim < 2 or P.shape[-2:] != (n, 3):
        raise ValueError(f"expected meshes of shape (..., {n}, 3), got {P.shape}")
    lead = P.shape[:-2]
    flat = P.reshape(-1, n, 3)
    return flat.transpose(1, 0, 2).reshape(n, -1), lead


def _meshes(X: np.ndarray, lead: tuple) -> np.ndarray:
    n = X.shape[0]
    return X.reshape(n, -1, 3).transpose(1, 0, 2).reshape(*lead, n, 3)


class Heat:
    """Frequency bands by heat diffusion on the template (implicit smoothing, Desbrun et al. 1999).

    Band j of P is (F_{j+1} - F_j)(P - mean) + mean, F the implicit heat-diffusion low-passes
    (M + tau L)^{-1} M from the smoothest (F_0 = 0, F_{C+1} = I); the bands' displacements sum to
    P - mean exactly, and ``assemble`` is their M-weighted least-squares synthesis.

    Args:
        k (int or list of int): cut points, as ``spectral``'s (dsm and pbs pass theirs): cut k
            diffuses for tau_k = 1 / sqrt(lambda_{k-1} lambda_k), halfway (geometrically)
            between the k-th and (k+1)-th smallest eigenvalues of L u = lambda M u; C cuts give
            C + 1 bands. Neither k nor t: k = 500.
        t (float or list of float): diffusion times instead, increasing, as fractions of the
            template's area (tau = t tr(M)); the largest gives the lowest band. No eigenvalues
            are computed. With k too (a model passing its cut points) both must give the same
            number of bands, and t sets the filters.
        mass (bool): M the mixed Voronoi mass matrix (true) or the identity (false).
    """

    name = "heat"

    def __init__(self, k: int | list[int] | None = None, t: float | list[float] | None = None, mass: bool = True):
        cuts = None
        if k is not None:
            cuts = [k] if isinstance(k, int) else list(k)
            if not cuts or any(isinstance(c, bool) or int(c) != c or c <= 0 for c in cuts) or cuts != sorted(set(cuts)):
                raise RecipeError(f"k: cut points must be positive increasing integers, got {k}")
            cuts = [int(c) for c in cuts]
        times = None
        if t is not None:
            times = [t] if isinstance(t, (int, float)) else list(t)
            if not times or any(isinstance(x, bool) or not float(x) > 0 or not np.isfinite(x) for x in times) \
                    or times != sorted(set(times)):
                raise RecipeError(f"t: diffusion times must be positive, finite and increasing, got {t}")
            times = [float(x) for x in times]
        if cuts is not None and times is not None and len(cuts) != len(times):
            raise RecipeError(f"t: {len(times)} diffusion times give {len(times) + 1} bands, but k = {k} asks for "
                              f"{len(cuts) + 1} (a model's k sets its band count): give {len(cuts)} times")
        if cuts is None and times is None:
            cuts = [DEFAULT_K]
        self.cuts, self.times, self.mass = cuts, times, bool(mass)
        self.mean = self.triangles = self.evals = self.null = None
        self._cache = None

    @property
    def n_bands(self) -> int:
        return len(self.times if self.times is not None else self.cuts) + 1

    # ------------------------------------------------------------------ fitting
    def fit(self, template, mean=None, cache=None) -> None:
        """Operators of the mean's geometry (``mean`` (n, 3); default the template's vertices) and
        one factorisation per cut; with ``k`` the eigenvalues up to the last cut, from
        ``cache`` (default: fwk's content-hash cache)."""
        n = template.n_vertices
        V = template.vertices if mean is None else np.asarray(mean, dtype=np.float64)
        if V.shape != (n, 3):
            raise RecipeError(f"mean: expected shape ({n}, 3), got {V.shape}")
        if self.times is None and self.cuts[-1] > n:
            raise RecipeError(f"k: cut point {self.cuts[-1]} exceeds the template's {n} vertices")
        self._cache = cache
        self.mean = V.copy()
        self.triangles = np.asarray(template.triangles, dtype=np.int64).copy()
        self.evals = self.null = None
        self._setup()
        if self.times is None:
            self._spectrum(self.cuts[-1])
        self._filters = [self._filter(c) for c in self._cut_order()]

    def _setup(self) -> None:
        self.L = cotangent_laplacian(self.mean, self.triangles)
        n = len(self.mean)
        self.m = mass_matrix(self.mean, self.triangles).diagonal().copy() if self.mass else np.ones(n)
        self._many: dict = {}

    def _cut_order(self) -> list:
        """The cut filters' keys from the smoothest: ("t", tau) by decreasing tau, or ("k", k)."""
        if self.times is not None:
            area = float(self.m.sum())
            return [("t", t * area) for t in sorted(self.times, reverse=True)]
        return [("k", c) for c in self.cuts]

    def _spectrum(self, K: int) -> None:
        """The eigenvalues lambda_0..lambda_K (as many as exist) and the zero ones' vectors."""
        n = len(self.mean)
        want = min(K + 1, n)
        if self.evals is not None and len(self.evals) >= want:
            return
        cache = self._cache if self._cache is not None else default_cache()
        zero = ZERO * float(np.mean(self.L.diagonal() / self.m))
        # at least one eigenvalue past the zeros (one per connected component), so that the
        # kernel projector of a cut at infinite time holds every component's constant
        want = min(max(want, int(connected_components(self.triangles, n).max()) + 2), n)
        while True:
            w, U = eigenbasis(self.mean, self.triangles, want, weighted=self.mass, cache=cache)
            w = np.maximum(np.asarray(w, dtype=np.float64), 0.0)
            if w[-1] > zero or want >= n:
                break
            want = min(2 * want, n)  # degenerate triangles: more zero eigenvalues than components
        nz = int((w <= zero).sum())
        w[:nz] = 0.0
        self.evals = w
        self.null = np.ascontiguousarray(U[:, :nz])

    def time_of_cut(self, k: int) -> float:
        """tau_k of cut k: inf for k <= the count of zero eigenvalues, 0 for k >= n (see the module)."""
        n = len(self.mean)
        if k >= n:
            return 0.0
        self._spectrum(k)
        lo, hi = self.evals[k - 1], self.evals[k]
        return np.inf if lo <= 0 else 1.0 / np.sqrt(lo * hi)

    def _filter(self, key) -> _LowPass:
        kind, v = key
        if kind == "k":
            if v <= 0:
                return _LowPass("zero", self.m)
            tau = self.time_of_cut(v)
        else:
            tau = v
        if tau == 0:
            return _LowPass("identity", self.m)
        if np.isinf(tau):
            return _LowPass("kernel", self.m, null=self.null)
        return _LowPass("heat", self.m, self.L, tau)

    def _check(self):
        if self.mean is None:
            raise RuntimeError("heat assembler used before fit()")

    # ------------------------------------------------------------------ bands
    def _band_columns(self, X: np.ndarray) -> list[np.ndarray]:
        """G_j X for every band j of (n, m) columns X."""
        lows = [F(X) for F in self._filters]
        return [lows[0], *(b - a for a, b in zip(lows, lows[1:])), X - lows[-1]]

    def split(self, P) -> list[np.ndarray]:
        """Bands of P (..., n, 3), each centred on the mean: band_j - mean sum to P - mean."""
        self._check()
        X, lead = _columns(np.asarray(P, dtype=np.float64) - self.mean, len(self.mean))
        return [_meshes(B, lead) + self.mean for B in self._band_columns(X)]

    def _normal(self, X: np.ndarray) -> np.ndarray:
        """sum_j G_j (G_j X): 2C solves."""
        Y = self._band_columns(X)
        out = Y[-1].copy()
        for i, F in enumerate(self._filters):  # sum_j (F_{j+1} - F_j) Y_j = Y_C + sum_i F_i (Y_{i-1} - Y_i)
            out += F(Y[i] - Y[i + 1])
        return out

    def assemble(self, bands) -> np.ndarray:
        """The M-weighted least-squares synthesis of per-band meshes (see the module):
        (sum_j G_j^2)^{-1} sum_j G_j (band_j - mean) + mean; ``assemble(split(P)) == P``."""
        self._check()
        if len(bands) != self.n_bands:
            raise ValueError(f"assemble: {len(bands)} bands given, the assembler has {self.n_bands}")
        n = len(self.mean)
        cols = [_columns(np.asarray(b, dtype=np.float64) - self.mean, n) for b in bands]
        lead = cols[0][1]
        Y = [c for c, _ in cols]
        if any(y.shape != Y[0].shape for y in Y):
            raise ValueError("assemble: the bands differ in shape")
        rhs = Y[-1].copy()
        for i, F in enumerate(self._filters):
            rhs += F(Y[i] - Y[i + 1])
        x = self._cg(rhs, sum(Y))
        return _meshes(x, lead) + self.mean

    def _cg(self, rhs: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Conjugate gradients for (sum_j G_j^2) x = rhs in the M-inner product, every column at once."""
        m = self.m

        def dot(u, v):
            return np.einsum("n,nc,nc->c", m, u, v)

        r = rhs - self._normal(x)
        p = r.copy()
        rr = dot(r, r)
        stop = CG_RTOL ** 2 * np.maximum(dot(rhs, rhs), 1e-300)
        for _ in range(CG_MAXITER):
            active = rr > stop
            if not active.any():
                break
            Ap = self._normal(p)
            pAp = dot(p, Ap)
            alpha = np.where(active & (pAp > 0), rr / np.where(pAp > 0, pAp, 1.0), 0.0)
            x = x + alpha * p
            r = r - alpha * Ap
            rr_new = dot(r, r)
            beta = np.where(active, rr_new / np.where(rr > 0, rr, 1.0), 0.0)
            p = r + beta * p
            rr = rr_new
        return x

    def band_shares(self, D) -> np.ndarray:
        """(..., n, 3) displacements D -> (..., bands): <G_j D, D>_M / ||D||_M^2, each band's share
        of their M-weighted energy (M = I with ``mass: false``); non-negative, summing to 1."""
        self._check()
        D = np.asarray(D, dtype=np.float64)
        X, lead = _columns(D, len(self.mean))
        b = X.shape[1] // 3

        def per_mesh(A, B):  # sum over vertices (M-weighted) and the 3 coordinates of each mesh
            return np.einsum("n,nc,nc->c", self.m, A, B).reshape(b, 3).sum(1)

        total = np.maximum(per_mesh(X, X), 1e-300)
        parts = np.stack([per_mesh(G, X) for G in self._band_columns(X)], -1)
        return (parts / total[:, None]).reshape(*lead, self.n_bands)

    def assemble_many(self, bands, ks) -> np.ndarray:
        """Two sources ``[low, high]`` (meshes, (b, n, 3) or (n, 3)) blended at every cut k of
        ``ks``: F_k (low - high) + high, (len(ks), b, n, 3); k = 0 gives ``high``, k >= n ``low``.
        One factorisation per distinct k (kept for later calls); with ``t`` the eigenvalues are
        computed on first use."""
        self._check()
        low, high = (np.asarray(x, dtype=np.float64) for x in bands)
        n = len(self.mean)
        if low.shape != high.shape:
            raise ValueError(f"assemble_many: sources of shapes {low.shape} and {high.shape}")
        X, lead = _columns(low - high, n)
        ks = [int(k) for k in ks]
        if any(k < 0 for k in ks):
            raise ValueError(f"assemble_many: every k must be >= 0, got {ks}")
        out = np.empty((len(ks), *high.shape))
        for i, k in enumerate(ks):
            F = self._many.get(k)
            if F is None:
                F = self._filter(("k", k))
                if len(self._many) >= FILTERS_KEPT:
                    self._many.pop(next(iter(self._many)))
                self._many[k] = F
            out[i] = _meshes(F(X), lead) + high
        return out

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        self._check()
        return {"cuts": self.cuts, "times": self.times, "mass": self.mass, "mean": self.mean,
                "triangles": self.triangles, "evals": self.evals, "null": self.null}

    def load_state_dict(self, d, ctx=None) -> None:
        """Restore a fitted assembler; the factorisations are recomputed (fast: no eigenvalues).
        ``ctx`` lends its cache to eigenvalues that a later ``assemble_many`` may need."""
        self.cuts = None if d["cuts"] is None else [int(c) for c in d["cuts"]]
        self.times = None if d["times"] is None else [float(x) for x in d["times"]]
        self.mass = bool(d["mass"])
        self.mean = np.asarray(d["mean"], dtype=np.float64)
        self.triangles = np.asarray(d["triangles"], dtype=np.int64)
        self.evals = None if d["evals"] is None else np.asarray(d["evals"], dtype=np.float64)
        self.null = None if d["null"] is None else np.asarray(d["null"], dtype=np.float64)
        self._cache = ctx.cache if ctx is not None else None
        self._setup()
        self._filters = [self._filter(c) for c in self._cut_order()]


@hookimpl
def fwk_register_assemblers():
    return [Heat]
