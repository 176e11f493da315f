"""The generalised eigenbasis of the cotangent Laplacian and spectral projection.

``eigenbasis(V, F, k)`` returns the k smallest eigenpairs of L u = lambda M u (thesis eq. 4.2;
``weighted=False``: L u = lambda u, eq. 4.1), M-orthonormal (U^T M U = I) with deterministic
signs (the largest-magnitude entry of each vector is positive).

Speed: scipy's ``eigsh(L, k, M, sigma)`` for k = 500 spends most of its time re-orthogonalising
a 1,001-vector Krylov basis (memory bound). fwk slices the spectrum instead (DESIGN.md,
reference notes): shift-invert Lanczos runs for about ``slice_size`` eigenpairs each, around
shifts that walk up the spectrum; each run factorises L - sigma M once (``ShiftedFactors``:
CHOLMOD's LDL^T when scikit-sparse is installed, else SuperLU). The nearest ``slice_size``
eigenvalues to a shift sigma fill an interval [sigma - d, sigma + d]; a slice is accepted only
when that interval reaches back to the last eigenvalue already found (so nothing is skipped),
otherwise the step shrinks and the slice is redone. Eigenvectors of a cluster split across two
slices are merged by a rank-revealing Rayleigh-Ritz step. With CHOLMOD, every accepted slice is
checked by Sylvester's law of inertia (the count of negative pivots of L - cM is the number of
eigenvalues below c); copies of a repeated eigenvalue that single-vector Lanczos missed are
then found by a further run with everything found so far deflated. Memory O(n k).

Projection never forms the n x n matrix X = U U^T M: ``SpectralProjector.project(P)`` applies
U (U^T (M P)) to all meshes and coordinates at once as one (n, 3b) block.
"""
from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import eigsh, splu, LinearOperator

from .operators import cotangent_laplacian, mass_matrix

try:  # optional (pip install scikit-sparse); a build against another NumPy fails with other errors
    from sksparse.cholmod import CholmodError, analyze
except Exception:
    CholmodError, analyze = None, None

ARPACK_TOL = 1e-12   # relative accuracy of the Ritz values of each slice
NCV_FACTOR = 1.5     # Lanczos basis size per slice: NCV_FACTOR x nev + 1 (1.5 measured faster than 2 here)


def _fix_signs(U: np.ndarray) -> np.ndarray:
    idx = np.argmax(np.abs(U), axis=0)
    s = np.sign(U[idx, np.arange(U.shape[1])])
    s[s == 0] = 1
    return U * s


def has_cholmod() -> bool:
    """Whether scikit-sparse's CHOLMOD is importable (optional: ``pip install scikit-sparse``)."""
    return analyze is not None


class ShiftedFactors:
    """Factorisations of A(sigma) = L - sigma M for one pair (L, M), with Sylvester's inertia.

    ``backend="cholmod"`` (scikit-sparse, when installed): one symbolic analysis, then a
    simplicial LDL^T per shift (no pivoting, so every solve's residual is checked and a shift
    whose factor is inaccurate falls back to SuperLU); the number of negative entries of D is
    the number of eigenvalues below sigma (Sylvester's law of inertia). ``"splu"``: SciPy's
    SuperLU with a COLAMD ordering (no inertia). ``"auto"``: CHOLMOD if importable."""

    def __init__(self, L, M, backend: str = "auto"):
        self.L, self.M = L.tocsc(), M.tocsc()
        if backend == "auto":
            backend = "cholmod" if has_cholmod() else "splu"
        if backend not in ("cholmod", "splu"):
            raise ValueError(f"backend must be auto, cholmod or splu, got {backend!r}")
        if backend == "cholmod" and not has_cholmod():
            raise ValueError("backend cholmod: scikit-sparse is not installed (pip install scikit-sparse)")
        self.backend = backend
        self._sym = None
        self._probe = np.random.default_rng(1).standard_normal(L.shape[0])

    def factor(self, sigma: float):
        """(solve, n_below): a solver for A(sigma) x = b and the eigenvalue count below sigma
        (None when unknown)."""
        A = (self.L - sigma * self.M).tocsc()
        if self.backend == "cholmod":
            try:
                if self._sym is None:
                    self._sym = analyze(A, mode="simplicial")
                f = self._sym.cholesky(A)
                b = self._probe
                x = f(b)
                # backward error of one solve: LDL^T without pivoting is not always stable
                if np.all(np.isfinite(x)) and np.linalg.norm(A @ x - b) <= 1e-10 * (
                        abs(A).sum(axis=0).max() * np.linalg.norm(x) + np.linalg.norm(b)):
                    return f, int((f.D() < 0).sum())
            except CholmodError:
                pass
        lu = splu(A, permc_spec="COLAMD")  # MMD_AT_PLUS_A: 35x slower to factor, 7x to solve (measured)
        return lu.solve, None


def _slice(fac: ShiftedFactors, sigma, nev, v0, deflate=None):
    """The ``nev`` eigenpairs nearest ``sigma`` (shift-invert Lanczos); ``deflate`` (n, d):
    M-orthonormal eigenvectors already known, projected out of the operator (they move to
    infinity), so that missing copies of a repeated eigenvalue can be found."""
    L, M = fac.L, fac.M
    solve, below = fac.factor(sigma)
    if deflate is not None and deflate.shape[1]:
        B, MB = deflate, M @ deflate
        inner = solve
        solve = lambda x: (lambda y: y - B @ (MB.T @ y))(inner(x))
        v0 = v0 - B @ (MB.T @ v0)
    op = LinearOperator(L.shape, matvec=solve, dtype=np.float64)
    nev = min(nev, L.shape[0] - 2 - (0 if deflate is None else deflate.shape[1]))
    w, U = eigsh(L, k=nev, M=M, sigma=sigma, OPinv=op, which="LM", v0=v0,
                 ncv=min(L.shape[0], int(NCV_FACTOR * nev) + 1), tol=ARPACK_TOL)
    o = np.argsort(w)
    return w[o], U[:, o], below


def generalized_eigs(L, M, k: int, slice_size: int = 60, seed: int = 0,
                     backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The k smallest eigenpairs of L u = lambda M u (see module doc).

    A mesh of several connected components (ICT-FaceKit's full head has 56) is solved one
    component at a time: the spectrum is the union of the components' spectra. Each component
    first gets a share of k proportional to its mass (Weyl's law: eigenvalue counts grow with
    area), plus a margin; a component whose largest computed eigenvalue lies below the k-th
    smallest of the union is asked for more until none does. ``backend``: see ShiftedFactors."""
    L = sp.csr_matrix(L)
    M = sp.csr_matrix(M)
    n_comp, labels = connected_components(L, directed=False)
    if n_comp == 1 or k >= L.shape[0] - 2:
        return _connected_eigs(L, M, k, slice_size, seed, backend)
    idx = [np.flatnonzero(labels == c) for c in range(n_comp)]
    mass = np.array([M.diagonal()[i].sum() for i in idx])
    want = [min(len(i), int(np.ceil(k * m / mass.sum() * 1.2)) + 4) for i, m in zip(idx, mass)]
    got: dict[int, tuple] = {}
    while True:
        for c, i in enumerate(idx):
            if c not in got or len(got[c][0]) < want[c]:
                Lc, Mc = L[i][:, i], M[i][:, i]
                got[c] = _connected_eigs(Lc, Mc, want[c], slice_size, seed, backend)
        allw = np.sort(np.concatenate([got[c][0] for c in got]))
        if len(allw) < k:
            grow = [c for c in got if len(got[c][0]) < len(idx[c])]
            for c in grow:
                want[c] = min(len(idx[c]), 2 * want[c])
            continue
        thresh = allw[k - 1]
        short = [c for c in got if len(got[c][0]) < len(idx[c]) and got[c][0][-1] <= thresh]
        if not short:
            break
        for c in short:
            want[c] = min(len(idx[c]), 2 * want[c])
    w = np.concatenate([got[c][0] for c in range(n_comp)])
    comp = np.concatenate([np.full(len(got[c][0]), c) for c in range(n_comp)])
    col = np.concatenate([np.arange(len(got[c][0])) for c in range(n_comp)])
    order = np.lexsort((col, comp, w))[:k]
    U = np.zeros((L.shape[0], k))
    for j, o in enumerate(order):
        c = comp[o]
        U[idx[c], j] = got[c][1][:, col[o]]
    return w[order], U


def _ritz(C, L, M):
    """Eigenpairs of L u = lambda M u restricted to the range of C: a rank-revealing
    M-orthonormal basis of that range, then Rayleigh-Ritz (the columns of C may be dependent,
    and mixtures of close eigenvalues are separated again)."""
    g, Q = np.linalg.eigh(C.T @ (M @ C))
    ok = g > 1e-8  # the columns have M-norm <= 1: a smaller remainder is round-off
    X = C @ (Q[:, ok] / np.sqrt(g[ok]))
    h, Z = np.linalg.eigh(X.T @ (L @ X))
    return h, X @ Z


def _connected_eigs(L, M, k: int, slice_size: int = 60, seed: int = 0, backend: str = "auto"):
    """The k smallest eigenpairs by spectrum slicing (one connected component or any mesh)."""
    n = L.shape[0]
    if k >= n - 2 or n <= 400:
        w, U = la.eigh(L.toarray(), M.toarray() if sp.issparse(M) else M)
        return w[:k], U[:, :k]
    if k <= 0:
        return np.zeros(0), np.zeros((n, 0))
    fac = ShiftedFactors(L, M, backend)
    M = fac.M
    v0 = np.random.default_rng(seed).standard_normal(n)
    scale = float((fac.L.diagonal() / M.diagonal()).mean())
    rel = lambda x: 1e-7 * max(abs(x), 1e-9 * scale)  # eigenvalues closer than this are one cluster
    # every slice asks for a margin of extra pairs and drops the farthest ones: Lanczos converges
    # last (and may miss copies of repeated eigenvalues) at the far end of a slice
    margin = lambda m: m + max(6, m // 10)
    vals, vecs = [], []
    found = -np.inf
    step = None
    while sum(len(x) for x in vals) < k:
        need = k - sum(len(x) for x in vals)
        nev = min(slice_size, k) if not vals else min(slice_size, max(need + 10, 20))
        sigma = -1e-6 * scale if not vals else found + step
        wa, Ua, _ = _slice(fac, sigma, margin(nev), v0)
        near_first = np.sort(np.argsort(np.abs(wa - sigma), kind="stable")[:nev])
        w, U = wa[near_first], Ua[:, near_first]
        if vals:
            d = np.max(np.abs(w - sigma))
            if sigma - d > found + rel(found) and len(w) >= nev:
                step *= 0.5  # the slice might not reach back to `found`: walk less far
                continue
        # keep eigenvalues beyond `found`, and merge the cluster at `found` by projection
        near = np.abs(w - found) <= rel(found) if vals else np.zeros(len(w), bool)
        new = w > found + rel(found) if vals else np.ones(len(w), bool)
        keep_w, keep_U = list(w[new]), [U[:, new]]
        if near.any():
            prev = np.concatenate(vecs, axis=1)
            pv = np.concatenate(vals)
            B = prev[:, np.abs(pv - found) <= rel(found)]
            C = U[:, near] - B @ (B.T @ (M @ U[:, near]))
            # what is left of the new copies is the part of the eigenspace not found yet: an
            # M-orthonormal basis of its range (rank-revealing; the copies are not independent)
            rw, rU = _ritz(C, fac.L, M)
            if len(rw):
                keep_w = list(rw) + keep_w
                keep_U = [rU] + keep_U
        if not keep_w:
            step *= 2.0
            continue
        kw = np.asarray(keep_w)
        top = kw.max()
        # Sylvester's inertia (CHOLMOD only): the count of eigenvalues below a point c under the
        # top cluster (a slice may cut through a multiplet; the next one completes it) must equal
        # what was found below c, or Lanczos missed copies of a repeated eigenvalue
        allw = np.concatenate([*vals, kw])
        lower = allw[allw < top - rel(top)]
        c = 0.5 * (lower.max() + allw[allw >= top - rel(top)].min()) if len(lower) else None
        have = len(lower)
        below = fac.factor(c)[1] if fac.backend == "cholmod" and c is not None else None
        tries = 0
        while below is not None and below > have and tries < 3:
            # single-vector Lanczos can miss copies of a repeated eigenvalue: look for them around
            # c with everything found so far deflated, and keep what lies below c
            tries += 1
            B = np.concatenate([*vecs, *keep_U], axis=1)
            wm, Um, _ = _slice(fac, c, (below - have) + 8 * tries, v0, deflate=B)
            sel = wm < c
            if sel.any():
                rw, rU = _ritz(Um[:, sel] - B @ ((M @ B).T @ Um[:, sel]), fac.L, M)
                keep_w = list(rw) + keep_w
                keep_U = [rU] + keep_U
                have += len(rw)
        if below is not None and below != have:
            warnings.warn(f"eigenbasis: {below} eigenvalues lie below {c:.6g} but {have} were found "
                          "(Sylvester inertia); the basis may miss copies of a repeated eigenvalue")
        kw = np.asarray(keep_w)
        top = kw.max()
        vals.append(kw)
        vecs.append(np.concatenate(keep_U, axis=1))
        found = top
        width = max(w[-1] - w[0], 1e-12 * scale)
        step = 0.45 * width if step is None else 0.45 * max(width, 0.5 * step / 0.45)
    w = np.concatenate(vals)
    U = np.concatenate(vecs, axis=1)
    o = np.argsort(w, kind="stable")[:k]
    return w[o], U[:, o]


def eigenbasis(V, F, k: int, weighted: bool = True, cache=None, slice_size: int = 60, backend: str = "auto"):
    """(evals (k,), U (n, k)): the k smallest eigenpairs of L u = lambda M u, M-orthonormal
    (eq. 4.2), or of L u = lambda u with U^T U = I (``weighted=False``, eq. 4.1); signs fixed so
    that each vector's largest-magnitude entry is positive. ``cache``: a ``fwk.cache.Cache``
    (keyed by positions, triangles, k and the options). ``backend``: see ``ShiftedFactors``."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    k = int(min(k, len(V)))

    def build():
        L = cotangent_laplacian(V, F)
        M = mass_matrix(V, F) if weighted else sp.identity(len(V), format="csc")
        w, U = generalized_eigs(L, M, k, slice_size, backend=backend)
        return w, _fix_signs(U)

    if cache is None:
        return build()
    return cache.get_or_build("eigenbasis", (V, F, k, weighted, slice_size, "v2"), build)


class SpectralProjector:
    """Projection onto eigenvector ranges without an n x n matrix.

    ``U`` (n, K) M-orthonormal eigenvectors, ``mass`` the diagonal of M (None: M = I).
    ``project(P, lo, hi)`` = U[:, lo:hi] (U[:, lo:hi]^T (M P)) for P (n, 3) or (b, n, 3), the
    batch folded into one (n, 3b) block; ``low(P, k)`` / ``high(P, k)`` the two bands."""

    def __init__(self, U: np.ndarray, mass: np.ndarray | None):
        self.U = np.ascontiguousarray(U)
        self.m = None if mass is None else np.asarray(mass, dtype=np.float64).reshape(-1)
        self.UtM = (self.U * self.m[:, None]).T.copy() if self.m is not None else self.U.T.copy()

    def coefficients(self, P):
        """(K, 3b) spectral coefficients U^T M P of P (n, 3) or (b, n, 3), the batch in the columns."""
        P = np.asarray(P, dtype=np.float64)
        b = P.reshape(-1, P.shape[-2], 3) if P.ndim == 3 else P[None]
        cols = b.transpose(1, 0, 2).reshape(b.shape[1], -1)  # (n, 3b): one product for the batch
        return self.UtM @ cols  # (K, 3b)

    def project(self, P, lo: int = 0, hi: int | None = None):
        """The part of P (n, 3) or (b, n, 3) in eigenvectors lo..hi-1: U[:, lo:hi] U[:, lo:hi]^T M
        P."""
        P = np.asarray(P, dtype=np.float64)
        single = P.ndim == 2
        b = P[None] if single else P
        cols = b.transpose(1, 0, 2).reshape(b.shape[1], -1)
        U = self.U[:, lo:hi]
        out = U @ (self.UtM[lo:hi] @ cols)
        out = out.reshape(b.shape[1], len(b), 3).transpose(1, 0, 2)
        return out[0] if single else out

    def low(self, P, k: int | None = None):
        """The first k eigenvectors' part of P (eq. 4.3 / 4.4): U_k U_k^T M P."""
        return self.project(P, 0, k)

    def high(self, P, k: int | None = None):
        """P minus its low part: (I - U_k U_k^T M) P."""
        return np.asarray(P, dtype=np.float64) - self.project(P, 0, k)
