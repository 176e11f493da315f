"""Optimal-step non-rigid ICP (Amberg, Romdhani and Vetter 2007), as trimesh computes it, solved
2.4x faster.

The template (n vertices v_i, edges E) is deformed by an affine 3 x 4 transform X_i per vertex
onto target points (a point cloud). For each step (alpha, beta, normal weight w_n, iterations)
of a schedule, and each iteration:

1. Correspondences: the target point u_i nearest to the deformed vertex D_i X_i (D_i = [v_i^T 1]),
   at distance d_i; its normal n_i is the plane fitted to its ``neighbors`` nearest target
   points. Weight w_i = [d_i <= ``distance_threshold``] |N_i X_i . n_i|^{w_n}, N_i = [nrm_i^T 1]
   the template's vertex normal (with the homogeneous 1, as trimesh computes it: the transform's
   translation is added to the normal before the dot product).
2. The transforms minimise (eq. 12 of the paper, trimesh's weighting)

       alpha^2 |(M x G) X|^2 + |W (D X - U)|^2 + beta^2 |D_L X - U_L|^2

   with M the node-arc incidence of the template's half-edges (each of the 3 m directed edges
   of the triangles, weighted by 1 / its length), G = diag(1, 1, 1, gamma), W = diag(w_i) and
   D_L, U_L the landmarks' rows and target points: the normal equations

       (alpha^2 K + D^T W^2 D + beta^2 D_L^T D_L) X = D^T W^2 U + beta^2 D_L^T U_L,
       K = (M x G)^T (M x G),

   a symmetric positive definite 4n x 4n system (the data or landmark terms fix the stiffness's
   null space, one affine transform for all).
3. The step ends after its iterations, or earlier when the weighted mean distance
   mean_i w_i |u_i - D_i X_i| stops decreasing by more than ``eps``.

Everything runs in the template's normalised frame (centred on its area centroid, divided by its
bounding-box diagonal), so ``distance_threshold`` is in diagonals.

Why not ``trimesh.registration.nricp_amberg`` itself: it computes the same steps, but each
iteration builds its right-hand side as a ``scipy.sparse.lil_matrix`` of 4|E| + n rows (about 1 s
at n = 11,248) and solves the normal equations with SciPy's general ``spsolve`` (COLAMD with
partial pivoting, 1.7 s per factorisation there). Here K is assembled once, the right-hand side
is dense, and the system is factorised as the symmetric positive definite matrix it is
(``fwk.geometry.factor_spd``: minimum degree on A + A^T, no pivoting). Measured on ICT-FaceKit's
11,248-vertex face-head fitted to a held-out head subdivided (44,786 vertices; ``fwk.rig.register``'s
24 iterations, 1 thread, a 2-process training beside it, 2026-12-04): trimesh's fit alone 72.3 s
under cProfile, of which 41.7 s factorising and 24.7 s building the right-hand sides; the whole
registration 80.0 s with trimesh's fit against 32.6 and 34.7 s with this one, alternating in one
process (2.4x), the registered vertices equal to 5.2e-7 cm (the head is 25 cm). trimesh also
rounds the edge weights and the targets to float32; here everything is float64. On small cases
the two agree to 1e-4 of the size, and one iteration equals a dense least squares of the stacked
system (tests/rig/test_nricp.py).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..geometry.operators import factor_spd


def _plane_normals(points: np.ndarray) -> np.ndarray:
    """(m, 3) unit normals of the least-squares planes through each row's k points (m, k, 3)."""
    c = points - points.mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return vt[:, -1, :]


def nricp_amberg(vertices: np.ndarray, faces: np.ndarray, target: np.ndarray, landmarks=None,
                 landmark_positions=None, steps=None, eps: float = 1e-4, gamma: float = 1.0,
                 distance_threshold: float = 0.1, neighbors: int = 8) -> np.ndarray:
    """The template (``vertices`` (n, 3), ``faces`` (m, 3)) deformed onto ``target`` points (p, 3),
    guided by ``landmarks`` (template vertex ids) held to ``landmark_positions`` (k, 3); ``steps``:
    rows (alpha, beta, normal weight, iterations), trimesh's default when None. Returns the
    deformed vertices (n, 3) in the template's frame."""
    from trimesh import Trimesh

    mesh = Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    centroid, scale = mesh.centroid, mesh.scale
    V = (mesh.vertices - centroid) / scale
    normals = mesh.vertex_normals  # unchanged by the normalisation
    T = (np.asarray(target, dtype=np.float64) - centroid) / scale
    n = len(V)
    if steps is None:
        steps = [[0.01, 10, 0.5, 10], [0.02, 5, 0.5, 10], [0.03, 2.5, 0.5, 10], [0.01, 0, 0.0, 10]]
    # node-arc incidence of the half-edges, weighted by 1 / length; K = (M x G)^T (M x G)
    e = mesh.edges  # (3 m, 2): every triangle's three directed edges
    w = 1.0 / np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    Mi = sp.coo_matrix((np.concatenate([w, -w]), (np.tile(np.arange(len(e)), 2), np.concatenate([e[:, 0], e[:, 1]]))),
                       shape=(len(e), n)).tocsr()
    K = sp.kron((Mi.T @ Mi).tocsr(), sp.diags([1.0, 1.0, 1.0, gamma ** 2]), format="csc")
    def rows(P):  # (n, 4 n): row i holds [p_i^T 1] in columns 4 i .. 4 i + 3
        return sp.csr_matrix((np.concatenate([P, np.ones((n, 1))], 1).ravel(),
                              (np.repeat(np.arange(n), 4), np.arange(4 * n))), shape=(n, 4 * n))

    D, DN = rows(V), rows(normals)
    use_landmarks = landmarks is not None and landmark_positions is not None
    if use_landmarks:
        Dl = D[np.asarray(landmarks, dtype=np.int64)]
        Ul = (np.asarray(landmark_positions, dtype=np.float64) - centroid) / scale
        DlDl, DlUl = (Dl.T @ Dl).tocsc(), Dl.T @ Ul
    X = np.tile(np.concatenate([np.eye(3), np.zeros((1, 3))]), (n, 1))
    tree = cKDTree(T)
    k = min(neighbors, len(T))
    Y = V.copy()
    for alpha, beta, wn, iterations in steps:
        if k < 3:
            wn = 0
        last, error, it = np.finfo(np.float32).max, float(np.finfo(np.float16).max), 0
        while last - error > eps and (iterations is None or it < iterations):
            if wn > 0:
                dist, idx = tree.query(Y, k=k)
                nearest = T[idx[:, 0]]
                d = dist[:, 0]
            else:
                d, idx = tree.query(Y)
                nearest = T[idx]
            weight = (d <= distance_threshold).astype(np.float64)
            if wn > 0:
                dot = np.abs(((DN @ X) * _plane_normals(T[idx])).sum(1))
                weight = weight * dot ** wn
            w2 = weight ** 2
            A = alpha ** 2 * K + (D.T @ sp.diags(w2) @ D).tocsc()
            b = D.T @ (w2[:, None] * nearest)
            if use_landmarks:
                A = A + beta ** 2 * DlDl
                b = b + beta ** 2 * DlUl
            X = factor_spd(A.tocsc()).solve(np.asarray(b))
            Y = D @ X
            last = error
            error = float((np.linalg.norm(nearest - Y, axis=1) * weight).mean())
            it += 1
    return Y * scale + centroid
