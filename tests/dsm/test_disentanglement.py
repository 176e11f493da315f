"""The edit task's like-with-like disentanglement measures (fwk_dsm_tasks module docstring) on
constructed band models whose answer is known: a perfectly disentangled pair of decoders (each
reads only its own band's code: cross-response 0, every edit inside its band) and a fully
entangled pair (each reads Z_own + Z_other: cross-response 1); band energies and training
variances against a dense eigendecomposition and loops."""
import numpy as np
import pytest
import scipy.linalg

from fwk.geometry.operators import cotangent_laplacian, mass_matrix
from fwk.plugins import get_registry
from fwk.recipes import make_spec
from fwk.runs import make_test_context

from test_dsm_model import NET, _data

REG = get_registry()
K, D = 20, 4  # the cut, latent entries per band


@pytest.fixture(scope="module")
def data():
    return _data(n_subjects=14, n_vertices=250)


@pytest.fixture(scope="module")
def assembled(data, tmp_path_factory):
    """A dsm model with its spectral bands fitted on the training mean (the networks never built)."""
    m = make_spec("model", {"name": "dsm", "network": NET, "k": K}, "dsm", REG).build()
    P = data.stack("train")
    m.template = data.template
    m._fit_assembler(data.template, P.mean(0), make_test_context(tmp_path_factory.mktemp("a")).cache)
    return m


def _toy(m, data, entangled: bool, fields=None):
    """The band model m with linear toy decoders in positions: P'_c(Z) = P-bar + sum_d w_d A_c[d]
    with w = Z_c (disentangled) or Z_c + Z_other (entangled); codes from a fixed draw."""
    import copy

    t = copy.copy(m)
    n = data.template.n_vertices
    mean = data.stack("train").mean(0)
    A = fields if fields is not None else np.random.default_rng(0).normal(size=(2, D, n, 3)) * 1e-2
    t.latents = [D, D]
    codes = np.random.default_rng(1).normal(size=(100, 2 * D))

    def decode_bands(z):
        z = np.atleast_2d(np.asarray(z, dtype=np.float64))
        zl, zh = z[:, :D], z[:, D:]
        out = []
        for c, own, other in ((0, zl, zh), (1, zh, zl)):
            w = own + other if entangled else own
            out.append(mean + np.einsum("bd,dni->bni", w, A[c]))
        return out

    t.decode_bands = decode_bands
    t.encode = lambda P: codes[: len(P)].copy()
    return t


def _env(data, models, tmp_path):
    from fwk_dsm_tasks import Env

    return Env(tmp_path, models, data.template, None, {"train": data.stack("train"), "test": data.stack("val")}, {})


def _settings(**kw):
    from fwk_dsm_tasks import EditSettings

    return EditSettings(**{"directions": [0, 1, 2, 3], "amounts": [-2, 0, 1.5], "max_subjects": 3, **kw})


@pytest.mark.parametrize("entangled", [False, True])
def test_cross_response_is_0_when_disentangled_and_1_when_fully_entangled(assembled, data, tmp_path, entangled):
    from fwk_dsm_tasks import measure_edits

    toy = _toy(assembled, data, entangled)
    res, *_ = measure_edits(_env(data, {"toy": toy}, tmp_path), _settings())
    r = res["dsm"]["toy"]
    rho = r["cross_response"]
    assert set(rho) == {"low<-high", "high<-low"}
    for v in rho.values():
        assert v == pytest.approx(1.0, abs=1e-9) if entangled else abs(v) < 1e-6
    if not entangled:  # every edit stays in its band, on either measure
        for b in ("low", "high"):
            assert r[b]["own_normalised_share"] == pytest.approx(1.0, abs=1e-9)
            assert r[b]["own_share"] == pytest.approx(1.0, abs=1e-9)
    else:  # an edit of either code moves both bands
        for b in ("low", "high"):
            assert 0.01 < r[b]["own_normalised_share"] < 0.99


def _dense_projectors(data):
    """X_low = U_K U_K^T M and X_high = I - X_low from a dense generalised eigendecomposition of
    the training mean's cotangent Laplacian (L u = lambda M u)."""
    mean = data.stack("train").mean(0)
    F = data.template.triangles
    L = cotangent_laplacian(mean, F).toarray()
    Mv = mass_matrix(mean, F).diagonal()
    lam, U = scipy.linalg.eigh(L, np.diag(Mv))
    assert lam[K] - lam[K - 1] > 1e-6 * lam[K]  # the cut is not inside a degenerate eigenspace
    X = U[:, :K] @ U[:, :K].T @ np.diag(Mv)
    return [X, np.eye(len(X)) - X], Mv


def test_band_energies_and_variances_against_a_dense_reference(assembled, data):
    from fwk_dsm_tasks import band_energies, band_variances

    Xs, Mv = _dense_projectors(data)
    P = data.stack("train")
    w = np.random.default_rng(2).uniform(0.5, 2.0, size=len(Mv))  # any per-vertex weights
    Dm = np.random.default_rng(3).normal(size=(2, 3, *P.shape[1:]))
    E = band_energies(assembled, Dm, w)
    assert E.shape == (2, 3, 2)
    for a in range(2):
        for b in range(3):
            for c in range(2):
                XD = Xs[c] @ Dm[a, b]
                want = sum(w[i] * float(XD[i] @ XD[i]) for i in range(len(w)))
                assert E[a, b, c] == pytest.approx(want, rel=1e-6)
    # with the Voronoi areas, the energies' shares are the band model's own band_shares
    E = band_energies(assembled, Dm, Mv)
    assert np.allclose(E / E.sum(-1, keepdims=True), assembled.band_shares(Dm), atol=1e-8)
    v = band_variances(assembled, P, Mv)
    mean = P.mean(0)
    for c in range(2):
        want = np.mean([sum(Mv[i] * float((Xs[c] @ (Ps - mean))[i] @ (Xs[c] @ (Ps - mean))[i])
                            for i in range(len(Mv))) for Ps in P])
        assert v[c] == pytest.approx(want, rel=1e-6)


def test_variance_units_of_an_edit_that_moves_a_band_like_a_training_subject(assembled, data, tmp_path):
    """An edit of one entry by 1 that moves band c by exactly training subject s's band-c
    displacement is worth e_c(X_c (P_s - P-bar)) / v_c variance units; its normalised share is 1."""
    from fwk_dsm_tasks import measure_edits

    Xs, Mv = _dense_projectors(data)
    P = data.stack("train")
    mean = P.mean(0)
    fields = np.zeros((2, D, *P.shape[1:]))
    for c in range(2):
        fields[c, 0] = Xs[c] @ (P[c] - mean)  # band c's decoder, entry 0: subject c's band-c displacement
    toy = _toy(assembled, data, entangled=False, fields=fields)
    res, *_ = measure_edits(_env(data, {"toy": toy}, tmp_path), _settings(directions=[0], amounts=[1.0]),
                            weights=Mv)
    for c, b in enumerate(("low", "high")):
        e = float(np.einsum("ni,ni,n->", fields[c, 0], fields[c, 0], Mv))
        v = np.mean([float(np.einsum("ni,ni,n->", Xs[c] @ (Ps - mean), Xs[c] @ (Ps - mean), Mv)) for Ps in P])
        r = res["dsm"]["toy"][b]
        assert r["variance_units"][b] == pytest.approx(e / v, rel=1e-6)
        assert r["normalised_shares"][b] == pytest.approx(1.0, abs=1e-9)
        assert res["dsm"]["toy"]["band_variance"][b] == pytest.approx(v, rel=1e-6)


def test_measures_from_energies_directly():
    """disentanglement_measures on hand-made energies: two edited bands, two edits each."""
    from fwk_dsm_tasks import disentanglement_measures

    E = {"low": np.array([[4.0, 1.0], [16.0, 1.0]]), "high": np.array([[1.0, 9.0], [1.0, 1.0]])}
    out = disentanglement_measures(E, [4.0, 1.0], ["low", "high"])
    lo = out["edits"]["low"]
    assert lo["variance_units"] == pytest.approx({"low": (1 + 4) / 2, "high": 1.0})
    assert lo["normalised_shares"]["low"] == pytest.approx((0.5 + 0.8) / 2)
    # rho_{low<-high} = mean sqrt(e_low | high edits) / mean sqrt(e_low | low edits) = 1 / 3
    assert out["cross_response"]["low<-high"] == pytest.approx(1.0 / 3.0)
    assert out["cross_response"]["high<-low"] == pytest.approx(1.0 / 2.0)
