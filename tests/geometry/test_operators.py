import math

import numpy as np
import pytest
import scipy.linalg as la
import trimesh

from fwk.geometry.operators import check_mesh, cotangent_laplacian, mass_matrix
from fwk.geometry.spectral import eigenbasis, generalized_eigs


def bumpy_sphere(sub=2, seed=0):
    m = trimesh.creation.icosphere(subdivisions=sub)
    rng = np.random.default_rng(seed)
    V = np.asarray(m.vertices) * (1 + 0.05 * rng.standard_normal((len(m.vertices), 1)))
    return V, np.asarray(m.faces)


def open_patch():
    V, F = bumpy_sphere(2)
    keep = V[F].mean(1)[:, 2] < 0.3  # an open cap with a border
    F = F[keep]
    used = np.unique(F)
    remap = -np.ones(len(V), int)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def naive_laplacian(V, F):
    n = len(V)
    L = np.zeros((n, n))
    for f in F:
        for k in range(3):
            i, j, o = f[(k + 1) % 3], f[(k + 2) % 3], f[k]
            u, v = V[i] - V[o], V[j] - V[o]
            cot = np.dot(u, v) / np.linalg.norm(np.cross(u, v))
            L[i, j] -= cot / 2
            L[j, i] -= cot / 2
    L -= np.diag(L.sum(1))
    return L


def naive_voronoi(V, F):
    n = len(V)
    A = np.zeros(n)
    for f in F:
        P = V[f]
        area = 0.5 * np.linalg.norm(np.cross(P[1] - P[0], P[2] - P[0]))
        ang = []
        for k in range(3):
            u, v = P[(k + 1) % 3] - P[k], P[(k + 2) % 3] - P[k]
            ang.append(math.acos(np.clip(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v), -1, 1)))
        for k in range(3):
            if max(ang) > math.pi / 2:
                A[f[k]] += area / 2 if ang[k] > math.pi / 2 else area / 4
            else:
                q, r = (k + 1) % 3, (k + 2) % 3
                A[f[k]] += (np.sum((P[k] - P[r]) ** 2) / math.tan(ang[q]) + np.sum((P[k] - P[q]) ** 2) / math.tan(ang[r])) / 8
    return A


@pytest.mark.parametrize("mesh", [bumpy_sphere, open_patch])
def test_laplacian_against_loops_and_properties(mesh):
    V, F = mesh()
    L = cotangent_laplacian(V, F)
    assert np.allclose(L.toarray(), naive_laplacian(V, F), atol=1e-12)
    assert abs(L - L.T).max() < 1e-14
    assert np.abs(np.asarray(L.sum(1))).max() < 1e-12
    assert np.linalg.eigvalsh(L.toarray()).min() > -1e-10  # positive semi-definite


@pytest.mark.parametrize("mesh", [bumpy_sphere, open_patch])
def test_mass_matrix_against_loops_and_area(mesh):
    V, F = mesh()
    area = trimesh.Trimesh(V, F, process=False).area
    Mv = mass_matrix(V, F).diagonal()
    Mb = mass_matrix(V, F, "barycentric").diagonal()
    assert np.allclose(Mv, naive_voronoi(V, F), rtol=1e-12)
    assert (Mv > 0).all() and (Mb > 0).all()
    assert Mv.sum() == pytest.approx(area, rel=1e-12) and Mb.sum() == pytest.approx(area, rel=1e-12)


def test_against_libigl():
    igl = pytest.importorskip("igl")
    V, F = open_patch()
    assert np.allclose(cotangent_laplacian(V, F).toarray(), -igl.cotmatrix(V, F).toarray(), atol=1e-10)
    Mi = igl.massmatrix(V, F, igl.MASSMATRIX_TYPE_VORONOI).diagonal()
    assert np.allclose(mass_matrix(V, F).diagonal(), Mi, rtol=1e-10)


def test_degenerate_and_isolated_guards():
    V, F = bumpy_sphere(1)
    V = np.vstack([V, [[5, 5, 5]]])  # an isolated vertex
    F = np.vstack([F, [[0, 0, 1]]])  # a degenerate triangle
    assert check_mesh(V, F) == {"degenerate_triangles": 1, "isolated_vertices": 1}
    L = cotangent_laplacian(V, F)
    M = mass_matrix(V, F).diagonal()
    assert np.all(np.isfinite(L.data)) and np.all(np.isfinite(M)) and (M > 0).all()
    w, U = eigenbasis(V, F, 10)
    assert np.all(np.isfinite(U)) and np.all(np.isfinite(w))


def test_eigenbasis_matches_dense_and_is_m_orthonormal():
    V, F = bumpy_sphere(3)  # 642 vertices: the slicing path
    L, M = cotangent_laplacian(V, F), mass_matrix(V, F)
    w, U = generalized_eigs(L, M, 150, slice_size=40)
    wd, Ud = la.eigh(L.toarray(), M.toarray())
    assert np.allclose(w, wd[:150], atol=1e-9)
    assert np.allclose(U.T @ (M @ U), np.eye(150), atol=1e-9)
    assert np.abs(L @ U - (M @ U) * w).max() < 1e-8
    # the spanned subspaces agree (repeated eigenvalues make single vectors arbitrary)
    P1 = U @ U.T @ M
    cut = 150 if wd[150] - wd[149] > 1e-6 else 149
    while wd[cut] - wd[cut - 1] < 1e-6:
        cut -= 1
    P2 = Ud[:, :cut] @ Ud[:, :cut].T @ M
    assert np.abs(P1 @ Ud[:, :cut] - Ud[:, :cut]).max() < 1e-6
    _ = P2


def test_eigenbasis_several_components_and_unweighted():
    V1, F1 = bumpy_sphere(2)
    V = np.vstack([V1, V1 + 3])
    F = np.vstack([F1, F1 + len(V1)])
    w, U = eigenbasis(V, F, 20)
    assert abs(w[0]) < 1e-9 and abs(w[1]) < 1e-9 and w[2] > 1e-3  # one zero per component
    M = mass_matrix(V, F)
    assert np.allclose(U.T @ (M @ U), np.eye(20), atol=1e-9)
    w0, U0 = eigenbasis(V, F, 20, weighted=False)
    assert np.allclose(U0.T @ U0, np.eye(20), atol=1e-9)
    # deterministic signs
    w2, U2 = eigenbasis(V, F, 20)
    assert np.array_equal(np.sign(U.max(0) + U.min(0)), np.sign(U2.max(0) + U2.min(0)))


def test_per_component_solve_matches_dense():
    V1, F1 = bumpy_sphere(3, seed=1)
    V2, F2 = bumpy_sphere(3, seed=2)
    V = np.vstack([V1, 2.0 * V2 + 5])  # a larger second component takes more of the spectrum
    F = np.vstack([F1, F2 + len(V1)])
    L, M = cotangent_laplacian(V, F), mass_matrix(V, F)
    w, U = generalized_eigs(L, M, 120, slice_size=40)
    wd = la.eigh(L.toarray(), M.toarray(), eigvals_only=True)
    assert np.allclose(w, wd[:120], atol=1e-9)
    assert np.allclose(U.T @ (M @ U), np.eye(120), atol=1e-9)
    assert np.abs(L @ U - (M @ U) * w).max() < 1e-8


def test_factor_spd_solves_as_a_dense_solve_and_as_colamd():
    """fwk.geometry.factor_spd (SuperLU ordered for symmetry, no pivoting) against numpy's dense
    solve and SciPy's default splu, on a cotangent Laplacian plus a mass term (SPD) of an open
    patch and on Deformation Transfer's kind of normal equations (A^T A of a random sparse A of
    full column rank); and it fills in less than COLAMD on the mesh."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from fwk.geometry import factor_spd

    V, F = open_patch()
    K = (cotangent_laplacian(V, F) + 0.1 * mass_matrix(V, F)).tocsc()
    rng = np.random.default_rng(0)
    A = sp.random(3 * len(V), len(V), density=4.0 / len(V), random_state=1, format="csr") + sp.eye(3 * len(V), len(V))
    for S in (K, (A.T @ A).tocsc()):
        b = rng.standard_normal((S.shape[0], 3))
        x = factor_spd(S).solve(b)
        dense = np.linalg.solve(S.toarray(), b)
        assert np.allclose(x, dense, rtol=1e-9, atol=1e-10 * np.abs(dense).max())
        assert np.allclose(x, splu(S, permc_spec="COLAMD").solve(b), rtol=1e-9, atol=1e-10 * np.abs(dense).max())
    f = factor_spd(K)
    c = splu(K, permc_spec="COLAMD")
    assert f.L.nnz + f.U.nnz < c.L.nnz + c.U.nnz
