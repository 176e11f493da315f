"""Cotangent Laplacian (thesis eq. 4.10) and mass matrices (Meyer et al. 2003), float64, sparse.

Conventions: L is positive semi-definite, L_ij = -(cot a_ij + cot b_ij) / 2 for an edge ij with
opposite angles a_ij, b_ij (one of them on a border edge), L_ii = -sum_j L_ij, so rows sum to
zero and x^T L x >= 0 (libigl's ``cotmatrix`` is -L). M is diagonal: ``voronoi`` gives the
mixed Voronoi area of Meyer et al. (for a non-obtuse triangle each corner gets its Voronoi
region (|PR|^2 cot Q + |PQ|^2 cot R) / 8; for an obtuse triangle the obtuse corner gets half
the area and the others a quarter), ``barycentric`` a third of each incident triangle's area.
Both sum to the surface area.

Guards (never NaN): a degenerate triangle (area <= ``1e-14`` x the mean area) contributes no
weight and no area; an isolated vertex (in no triangle, or only in degenerate ones) gets a zero
Laplacian row and the mean vertex area as its mass, so the generalised eigenproblem stays
positive definite in M (it shows up as one extra zero eigenvalue). ``check_mesh`` reports both.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

DEGENERATE = 1e-14


def _corner_data(V, F):
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    P = [V[F[:, k]] for k in range(3)]
    cross = np.cross(P[1] - P[0], P[2] - P[0])
    dbl = np.linalg.norm(cross, axis=1)  # twice the area
    area = 0.5 * dbl
    ok = dbl > DEGENERATE * max(dbl.mean(), 1e-300)
    cots = np.zeros((len(F), 3))
    for k in range(3):
        u = P[(k + 1) % 3] - P[k]
        v = P[(k + 2) % 3] - P[k]
        cots[:, k] = np.where(ok, np.einsum("ij,ij->i", u, v) / np.where(ok, dbl, 1.0), 0.0)
    return P, area, ok, cots


def cotangent_laplacian(V, F) -> sp.csr_matrix:
    """(n, n) positive semi-definite cotangent Laplacian (eq. 4.10)."""
    n = len(V)
    F = np.asarray(F, dtype=np.int64)
    _, _, _, cots = _corner_data(V, F)
    rows, cols, vals = [], [], []
    for k in range(3):  # the corner k is opposite edge (k+1, k+2)
        i, j = F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        w = 0.5 * cots[:, k]
        rows += [i, j]
        cols += [j, i]
        vals += [-w, -w]
    W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    W.sum_duplicates()
    L = W - sp.diags(np.asarray(W.sum(axis=1)).ravel())
    return L.tocsr()


def mass_matrix(V, F, kind: str = "voronoi") -> sp.dia_matrix:
    """Diagonal (n, n) mass matrix: mixed Voronoi (Meyer 2003) or barycentric areas."""
    n = len(V)
    F = np.asarray(F, dtype=np.int64)
    P, area, ok, cots = _corner_data(V, F)
    if kind == "barycentric":
        A = np.repeat((area * ok / 3.0)[:, None], 3, axis=1)
    elif kind == "voronoi":
        A = np.zeros((len(F), 3))
        sq = [np.einsum("ij,ij->i", P[(k + 2) % 3] - P[(k + 1) % 3], P[(k + 2) % 3] - P[(k + 1) % 3]) for k in range(3)]
        # sq[k]: squared length of the edge opposite corner k
        obtuse = cots < 0  # cot < 0 <=> angle > 90 degrees
        any_obt = obtuse.any(axis=1)
        for k in range(3):
            k1, k2 = (k + 1) % 3, (k + 2) % 3
            vor = (sq[k2] * cots[:, k2] + sq[k1] * cots[:, k1]) / 8.0
            A[:, k] = np.where(any_obt, np.where(obtuse[:, k], area / 2, area / 4), vor)
        A *= ok[:, None]
    else:
        raise ValueError(f"mass_matrix: kind must be voronoi or barycentric, got {kind!r}")
    m = np.bincount(F.ravel(), A.ravel(), minlength=n)
    isolated = m <= 0
    if isolated.any():
        m[isolated] = m[~isolated].mean() if (~isolated).any() else 1.0
    return sp.diags(m).todia()


def check_mesh(V, F) -> dict:
    """Counts of degenerate triangles and isolated vertices (the guards above apply to them)."""
    _, _, ok, _ = _corner_data(V, F)
    used = np.zeros(len(V), bool)
    used[np.asarray(F)[ok].ravel()] = True
    return {"degenerate_triangles": int((~ok).sum()), "isolated_vertices": int((~used).sum())}


def face_areas(V, F) -> np.ndarray:
    """(m,) triangle areas; batched: V (b, n, 3) -> (b, m)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    P0, P1, P2 = V[..., F[:, 0], :], V[..., F[:, 1], :], V[..., F[:, 2], :]
    return 0.5 * np.linalg.norm(np.cross(P1 - P0, P2 - P0), axis=-1)


def vertex_normals(V, F, chunk: int = 8, dtype=np.float64, fallback=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n, 3) unit vertex normals, the area-weighted mean of the incident face normals (the sum of
    the incident triangles' cross products, normalised); batched: V (b, n, 3) -> (b, n, 3). A vertex
    with no area (in no non-degenerate face) gets ``fallback``. The stack goes ``chunk`` shapes at
    a time, vertex-major (each triangle corner one contiguous row gather), the cross product
    written out by component: a 51-shape rig of ICT-FaceKit's full head took 6.1 s with np.cross
    on the whole stack in a fresh process (most of it touching ~0.5 GB of new temporaries), 0.9 s
    so. ``dtype``: the arithmetic's (float32 for a file that stores float32 normals)."""
    V = np.asarray(V, dtype=dtype)
    F = np.asarray(F, dtype=np.int64)
    stack = V if V.ndim == 3 else V[None]
    S, n = stack.shape[:2]
    m = len(F)
    inc = sp.csr_matrix((np.ones(3 * m, dtype=dtype), (F.T.reshape(-1), np.tile(np.arange(m), 3))), shape=(n, m))
    out = np.empty((S, n, 3), dtype=dtype)
    t0, t1, t2 = (np.ascontiguousarray(F[:, k]) for k in range(3))
    for s0 in range(0, S, chunk):
        X = np.ascontiguousarray(stack[s0:s0 + chunk].transpose(1, 0, 2))  # (n, c, 3)
        c = X.shape[1]
        a = X[t0]
        e1, e2 = X[t1] - a, X[t2] - a  # (m, c, 3)
        fn = np.empty_like(e1)
        fn[..., 0] = e1[..., 1] * e2[..., 2] - e1[..., 2] * e2[..., 1]
        fn[..., 1] = e1[..., 2] * e2[..., 0] - e1[..., 0] * e2[..., 2]
        fn[..., 2] = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
        N = (inc @ fn.reshape(m, 3 * c)).reshape(n, c, 3)
        norm = np.sqrt(np.einsum("nck,nck->nc", N, N))[..., None]
        ok = norm[..., 0] > 0
        part = np.broadcast_to(np.asarray(fallback, dtype=dtype), N.shape).copy()
        part[ok] = N[ok] / norm[ok]
        out[s0:s0 + c] = part.transpose(1, 0, 2)
    return out if V.ndim == 3 else out[0]


def factor_spd(A):
    """SuperLU factors (``scipy.sparse.linalg.splu``; ``.solve(b)``) of a sparse symmetric
    positive definite A, ordered for symmetry: the minimum degree ordering of A + A^T applied to
    rows and columns alike, no partial pivoting (``diag_pivot_thresh=0``, ``SymmetricMode``: SPD
    needs none). SciPy's default, COLAMD with partial pivoting, orders for an unsymmetric A: on
    Deformation Transfer's 18,167 x 18,167 normal equations (a 6,080-vertex head) it filled in
    1.86 M non-zeros and factored in 0.124 s, this 0.53 M in 0.034 s, and solved 3.6x faster
    (``benchmarks/pipeline.py``). The solutions agree to rounding (tested against a dense
    solve). Not for indefinite or unsymmetric matrices: without pivoting their factors may be
    unstable (use ``splu`` itself)."""
    from scipy.sparse.linalg import splu

    return splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                options={"SymmetricMode": True})
