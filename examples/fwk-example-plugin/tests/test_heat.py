"""The heat-diffusion assembler passes fwk's assembler contract suite (cut points and explicit
times, with and without the mass matrix), equals dense solves of (M + tau L) X = M P written out
with a hand-built cotangent Laplacian, keeps translations in its low band, and splits Deep
Spectral Meshes' bands from a recipe."""
import json

import numpy as np
import pytest
import scipy.linalg as la
import trimesh

from fwk.data import Template
from fwk.errors import RecipeError
from fwk.geometry.operators import mass_matrix
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import Assembler, BandModel
from fwk.testing.assembler import AssemblerContract
from fwk.testing.sampler import two_components
from fwk_example_plugin.heat import Heat
from recipe_runs import assert_tested, run_recipe, tiny_recipe


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "fwk-cache"))  # eigenvalues not in the user's cache


class TestTwoBands(AssemblerContract):
    component = Heat
    params = {"k": 10}


class TestThreeBands(AssemblerContract):
    component = Heat
    params = {"k": [4, 20]}


class TestExplicitTimes(AssemblerContract):
    component = Heat  # no eigenvalues for the split; assemble_many's cut points compute them when asked
    params = {"t": [0.002, 0.02]}


class TestNoMass(AssemblerContract):
    component = Heat
    params = {"k": 12, "mass": False}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("assembler", "heat")
    assert e.component is Heat and e.plugin == "example-heat"


# ---------------------------------------------------------------- dense references

def _mesh(subdivisions=1):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    V = np.asarray(m.vertices) * [1.0, 1.4, 0.7]
    return Template(V, np.asarray(m.faces)), V


def _naive_cot_laplacian(V, F):
    """L_ij = -(cot a_ij + cot b_ij) / 2, L_ii = -sum_j L_ij, a loop over triangle corners."""
    n = len(V)
    L = np.zeros((n, n))
    for tri in F:
        for c in range(3):
            o, i, j = tri[c], tri[(c + 1) % 3], tri[(c + 2) % 3]  # corner o opposite edge (i, j)
            u, v = V[i] - V[o], V[j] - V[o]
            cot = u @ v / np.linalg.norm(np.cross(u, v))
            L[i, j] -= cot / 2
            L[j, i] -= cot / 2
    L[np.diag_indices(n)] = -L.sum(1)
    return L


def _dense(template, V, mass=True):
    L = _naive_cot_laplacian(V, template.triangles)
    m = mass_matrix(V, template.triangles).diagonal() if mass else np.ones(len(V))
    return L, np.diag(m)


def _heat(L, M, tau):
    return np.linalg.solve(M + tau * L, M)  # H = (M + tau L)^-1 M, dense


@pytest.mark.parametrize("mass", [True, False])
def test_low_band_is_a_dense_solve_of_the_implicit_heat_step(mass):
    t, V = _mesh()
    a = Heat(k=8, mass=mass)
    a.fit(t, V)
    L, M = _dense(t, V, mass)
    w = la.eigh(L, M, eigvals_only=True)  # lambda_0 <= lambda_1 <= ...
    tau = 1.0 / np.sqrt(w[7] * w[8])  # geometric midpoint of the 8th and 9th eigenvalues
    assert np.isclose(a.time_of_cut(8), tau, rtol=1e-6)
    P = V + np.random.default_rng(0).normal(0, 0.05, (2, *V.shape))
    low, high = a.split(P)
    for s in range(2):
        X = np.linalg.solve(M + tau * L, M @ (P[s] - V))  # (M + tau L) X = M (P - mean)
        assert np.allclose(low[s] - V, X, atol=1e-8)
        assert np.allclose(high[s] - V, P[s] - V - X, atol=1e-8)
    assert np.allclose(low + high - V, P, atol=1e-12)  # the bands sum back to P exactly


def test_explicit_times_are_fractions_of_the_area_and_order_the_bands():
    t, V = _mesh()
    a = Heat(t=[0.001, 0.01, 0.1])
    a.fit(t, V)
    assert a.evals is None  # no eigenvalues needed
    L, M = _dense(t, V)
    area = np.trace(M)
    F = [_heat(L, M, x * area) for x in (0.1, 0.01, 0.001)]  # from the smoothest
    D = np.random.default_rng(1).normal(0, 0.05, V.shape)
    bands = a.split(V + D)
    ref = [F[0] @ D, (F[1] - F[0]) @ D, (F[2] - F[1]) @ D, D - F[2] @ D]
    assert len(bands) == 4
    for b, r in zip(bands, ref):
        assert np.allclose(b - V, r, atol=1e-8)


def test_assemble_is_the_m_weighted_least_squares_synthesis():
    t, V = _mesh()
    a = Heat(k=[3, 15])
    a.fit(t, V)
    L, M = _dense(t, V)
    F = [np.zeros_like(L), _heat(L, M, a.time_of_cut(3)), _heat(L, M, a.time_of_cut(15)), np.eye(len(V))]
    G = [F[j + 1] - F[j] for j in range(3)]
    rng = np.random.default_rng(2)
    Y = [rng.normal(0, 0.05, V.shape) for _ in G]  # per-band reconstructions that are no split
    # argmin_D sum_j ||G_j D - y_j||_M^2: normal equations sum_j G_j^T M G_j D = sum_j G_j^T M y_j
    A = sum(g.T @ M @ g for g in G)
    D = np.linalg.solve(A, sum(g.T @ M @ y for g, y in zip(G, Y)))
    got = a.assemble([y + V for y in Y])
    assert np.allclose(got - V, D, atol=1e-9)


def test_assemble_many_blends_with_the_cut_filter():
    t, V = _mesh()
    a = Heat(k=10)
    a.fit(t, V)
    L, M = _dense(t, V)
    rng = np.random.default_rng(3)
    lo, hi = V + rng.normal(0, 0.05, (2, *V.shape)), V + rng.normal(0, 0.05, (2, *V.shape))
    ks = [0, 1, 4, 10, len(V)]
    out = a.assemble_many([lo, hi], ks)
    assert np.allclose(out[0], hi) and np.allclose(out[-1], lo)  # k = 0: all high; k = n: all low
    Mw = np.diag(M)
    const = (Mw @ (lo - hi)) / Mw.sum()  # k = 1 (one component): the M-weighted mean of low - high
    assert np.allclose(out[1], hi + const[:, None, :], atol=1e-10)
    for i, k in ((2, 4), (3, 10)):
        H = _heat(L, M, a.time_of_cut(k))
        assert np.allclose(out[i], np.einsum("ij,bjc->bic", H, lo - hi) + hi, atol=1e-9)
    single = a.assemble_many([lo[0], hi[0]], ks)
    assert single.shape == (len(ks), len(V), 3) and np.allclose(single, out[:, 0])


def test_band_shares_are_the_bands_m_inner_products():
    t, V = _mesh()
    a = Heat(k=[4, 20])
    a.fit(t, V)
    L, M = _dense(t, V)
    F = [np.zeros_like(L), _heat(L, M, a.time_of_cut(4)), _heat(L, M, a.time_of_cut(20)), np.eye(len(V))]
    D = np.random.default_rng(4).normal(0, 0.05, (3, *V.shape))
    s = a.band_shares(D)
    assert s.shape == (3, 3) and (s >= -1e-12).all() and np.allclose(s.sum(-1), 1.0)
    for b in range(3):
        total = np.sum(np.diag(M)[:, None] * D[b] ** 2)
        ref = [np.sum(D[b] * (M @ ((F[j + 1] - F[j]) @ D[b]))) / total for j in range(3)]
        assert np.allclose(s[b], ref, atol=1e-10)
    assert a.band_shares(D[0]).shape == (3,)


# ---------------------------------------------------------------- properties

@pytest.mark.parametrize("params", [{"k": 10}, {"k": [3, 30]}, {"t": 0.01}, {"k": 10, "mass": False}])
def test_translations_lie_wholly_in_the_low_band(params):
    t, V = _mesh(2)
    a = Heat(**params)
    a.fit(t, V)
    c = np.array([0.3, -1.2, 2.0])
    bands = a.split((V + c)[None])
    assert np.allclose(bands[0][0], V + c, atol=1e-10)  # the constant displacement: all low
    assert all(np.allclose(b[0], V, atol=1e-10) for b in bands[1:])
    P = V + np.random.default_rng(5).normal(0, 0.02, (2, *V.shape))  # a rigid translation of any mesh
    moved, still = a.split(P + c), a.split(P)
    assert np.allclose(moved[0], still[0] + c, atol=1e-10)
    assert all(np.allclose(x, y, atol=1e-10) for x, y in zip(moved[1:], still[1:]))
    assert np.allclose(a.band_shares(np.broadcast_to(c, V.shape))[0], 1.0)


def test_the_cut_halves_the_spectrum_where_spectral_cuts_it():
    """Eigenvectors below cut k have more than half their energy in the low band, those above it
    less: the meaning of k carried over from the spectral assembler."""
    t, V = _mesh(2)
    k = 12
    a = Heat(k=k)
    a.fit(t, V)
    L, M = _dense(t, V)
    w, U = la.eigh(L, M)
    shares = a.band_shares(U[:, :40].T[:, :, None] * np.ones(3))[:, 0]
    gap = w[k] > w[k - 1] * (1 + 1e-6)
    assert (shares[:k] >= 0.5 - 1e-9).all() and (shares[k:] <= 0.5 + 1e-9).all() and gap
    assert shares[0] == pytest.approx(1.0) and np.all(np.diff(shares) <= 1e-9)  # monotone in frequency


def test_infinite_time_keeps_each_components_constant():
    """k = 1 on a template of two components: both components' zero eigenvalues give tau = inf,
    the low band the M-weighted mean displacement of each component (no solve of a singular system)."""
    t = two_components()
    V = t.vertices
    a = Heat(k=2)
    a.fit(t, V)
    assert np.isinf(a.time_of_cut(1)) and np.isinf(a.time_of_cut(2)) and a.null.shape[1] == 2
    D = np.random.default_rng(6).normal(0, 0.05, V.shape)
    low = a.split(V + D)[0] - V
    m = mass_matrix(V, t.triangles).diagonal()
    for c in (0, 1):
        idx = t.components == c
        assert np.allclose(low[idx], (m[idx] @ D[idx]) / m[idx].sum(), atol=1e-10)
    assert np.allclose(a.assemble(a.split(V + D)), V + D, atol=1e-10)


def test_split_assemble_exact_on_a_real_head():
    t = get_registry().get("dataset", "synthetic-heads")(n_subjects=3, n_vertices=400).load(None).template
    a = Heat(k=[20, 80])
    a.fit(t, t.vertices)
    P = t.vertices + np.random.default_rng(7).normal(0, 0.05, (3, t.n_vertices, 3))
    assert np.allclose(a.assemble(a.split(P)), P, atol=1e-10)


@pytest.mark.parametrize("params, match", [
    ({"k": 0}, "k: cut points must be positive increasing"),
    ({"k": [20, 10]}, "k: cut points must be positive increasing"),
    ({"t": -0.1}, "t: diffusion times must be positive"),
    ({"t": [0.1, 0.01]}, "t: diffusion times must be positive, finite and increasing"),
    ({"k": 30, "t": [0.01, 0.1]}, r"t: 2 diffusion times give 3 bands, but k = 30 asks for 2"),
])
def test_bad_parameters_are_recipe_errors(params, match):
    with pytest.raises(RecipeError, match=match):
        Heat(**params)


def test_cut_beyond_the_template_is_a_recipe_error():
    t, V = _mesh()
    with pytest.raises(RecipeError, match=f"k: cut point 500 exceeds the template's {len(V)} vertices"):
        Heat().fit(t, V)


def test_used_before_fit_says_so():
    with pytest.raises(RuntimeError, match="before fit"):
        Heat(k=3).split(np.zeros((1, 4, 3)))
    assert isinstance(Heat(k=3), Assembler)


# ---------------------------------------------------------------- in a model

RECIPE = tiny_recipe("""
dsm-heat:
  name: dsm
  k: 30
  assembler: heat
  network: {name: vae, conv: {name: spiral++, length: 9}, channels: [8, 16], latent: 8,
            sampler: {name: quadric, factors: [4, 4]}}
dsm-heat-times:
  name: dsm
  k: [10, 60]
  assembler: {name: heat, t: [0.002, 0.02]}
  network: {name: vae, conv: {name: spiral++, length: 9}, channels: [8, 16], latent: 8,
            sampler: {name: quadric, factors: [4, 4]}}
""")


def test_heat_splits_deep_spectral_meshes_bands(tmp_path):
    run_dir = run_recipe(tmp_path, "heat.yaml", RECIPE)  # FWK_CACHE stays _own_cache's
    assert_tested(run_dir, {"dsm-heat", "dsm-heat-times"}, only=True)
    run = open_run(run_dir)  # reopened: the assembler's state restores the same bands
    for label, n_bands in (("dsm-heat", 2), ("dsm-heat-times", 3)):
        model = run.model(label)
        assert isinstance(model, BandModel) and isinstance(model.assembler, Heat)
        assert len(model.band_names) == n_bands
        P = model.sample(2, seed=0)
        bands = model.split(P)
        assert len(bands) == n_bands and np.allclose(model.assemble(bands), P, atol=1e-8)
        assert np.allclose(model.band_shares(P - model.assembler.mean).sum(-1), 1.0)


PBS_RECIPE = tiny_recipe("""
pbs-heat:
  name: pbs
  assembler: heat
  ks: [0, 5, 20, 60, 400]
  network: {name: vae, conv: {name: spiral++, length: 9}, channels: [8, 16], latent: 8,
            sampler: {name: quadric, factors: [4, 4]}}
""", task="blendshapes", shapes=["neutral", "mouth-wide"], kl_weight=None)


def test_heat_assembles_personalised_blendshapes_at_every_k_of_the_sweep(tmp_path):
    """pbs's Pareto k sweep calls assemble_many over its ks (0 and >= n included)."""
    run_dir = run_recipe(tmp_path, "pbs.yaml", PBS_RECIPE)
    m = json.loads((run_dir / "metrics.json").read_text())
    assert "pbs-heat" in json.dumps(m)
    run = open_run(run_dir)
    model = run.model("pbs-heat")
    assert isinstance(model.assembler, Heat)
    n = model.template.n_vertices
    assert model.k["mouth-wide"] in (0, 5, 20, 60, n)  # 400 clamped to the template's n
    Ps, Pd = model.branches(model.template.vertices[None], "mouth-wide")
    out = model.assemble(Ps, Pd, [0, 5, n])
    assert np.allclose(out[0], Pd) and np.allclose(out[2], Ps)  # k = 0: the differential branch, k = n: spatial
    assert np.allclose(out[1], model.assembler.assemble_many([Ps, Pd], [5])[0])
