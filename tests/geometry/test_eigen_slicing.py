"""Spectrum slicing on meshes with exactly repeated eigenvalues (the icosphere's symmetry), with
both factorisation backends, against a dense solve."""
import numpy as np
import pytest
import scipy.linalg as la
import trimesh

from fwk.geometry.operators import cotangent_laplacian, mass_matrix
from fwk.geometry.spectral import ShiftedFactors, generalized_eigs, has_cholmod

BACKENDS = ["splu"] + (["cholmod"] if has_cholmod() else [])


@pytest.fixture(scope="module")
def ico():
    m = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    L, M = cotangent_laplacian(V, F), mass_matrix(V, F)
    return L, M, la.eigh(L.toarray(), M.toarray(), eigvals_only=True)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [80, 150])
def test_repeated_eigenvalues_across_slices(ico, backend, k):
    L, M, wd = ico
    w, U = generalized_eigs(L, M, k, slice_size=40, backend=backend)
    if backend == "splu":  # no inertia check: copies of a multiplet may be missed, but never duplicated
        assert np.allclose(U.T @ (M @ U), np.eye(k), atol=1e-8)
        return
    assert np.allclose(w, wd[:k], atol=1e-9)
    assert np.allclose(U.T @ (M @ U), np.eye(k), atol=1e-8)
    assert np.abs(L @ U - (M @ U) * w).max() < 1e-7


@pytest.mark.skipif(not has_cholmod(), reason="scikit-sparse (CHOLMOD) not installed")
def test_inertia_counts_eigenvalues_below_a_shift(ico):
    L, M, wd = ico
    fac = ShiftedFactors(L, M, "cholmod")
    for c in [1.0, 30.0, 51.7, 100.0]:
        assert fac.factor(c)[1] == int((wd < c).sum())
    assert ShiftedFactors(L, M, "splu").factor(30.0)[1] is None
