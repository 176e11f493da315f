"""The eigenbasis on the real ICT-FaceKit face-head region (11,248 vertices), k = 500: residuals,
M-orthonormality, and (with CHOLMOD) Sylvester's inertia confirming that exactly the k smallest
eigenvalues were found. Also the full head (26,719 vertices, 56 pieces) at a smaller k."""
import numpy as np
import pytest

from fwk.geometry.operators import cotangent_laplacian, mass_matrix
from fwk.geometry.spectral import ShiftedFactors, generalized_eigs, has_cholmod
from fwk.testing import ICT_SKIP_REASON, ict_path


def _ict(region):
    folder = ict_path()
    if folder is None:
        pytest.skip(ICT_SKIP_REASON)
    from fwk.cache import Cache
    from fwk.plugins import get_registry

    col = get_registry().get("dataset", "ict-facekit")(path=str(folder), n_subjects=1, region=region).load(Cache())
    return col.template


def _check(t, k):
    L, M = cotangent_laplacian(t.vertices, t.triangles), mass_matrix(t.vertices, t.triangles)
    w, U = generalized_eigs(L, M, k)
    assert np.all(np.diff(w) >= -1e-12) and abs(w[0]) < 1e-8
    assert np.abs(U.T @ (M @ U) - np.eye(k)).max() < 1e-8
    assert np.abs(L @ U - (M @ U) * w).max() < 1e-6 * max(1.0, w[-1])
    if has_cholmod():
        gap = w[-1] - w[w < w[-1] * (1 - 1e-6)].max()
        below = ShiftedFactors(L, M, "cholmod").factor(w[-1] - 0.5 * gap)[1]
        assert below == int((w < w[-1] * (1 - 1e-6)).sum())


@pytest.mark.slow
def test_face_head_k500():
    _check(_ict("face-head"), 500)


@pytest.mark.slow
def test_full_head_several_components():
    _check(_ict("full"), 200)
