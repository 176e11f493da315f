import numpy as np
import pytest
import trimesh

from fwk.data import Template
from fwk.plugins import get_registry
from fwk.testing.assembler import AssemblerContract

Spectral = get_registry().get("assembler", "spectral")


class TestTwoBands(AssemblerContract):
    component = Spectral
    params = {"k": 30}


class TestThreeBands(AssemblerContract):
    component = Spectral
    params = {"k": [10, 40]}


class TestNoMass(AssemblerContract):
    component = Spectral
    params = {"k": 25, "mass": False}


def _fitted(k):
    m = trimesh.creation.icosphere(subdivisions=3)
    V = np.asarray(m.vertices)
    t = Template(V, np.asarray(m.faces))
    a = Spectral(k=k)
    a.fit(t, V)
    return a, V


def test_band_filters_out_what_lies_outside_it():
    a, V = _fitted([20, 60])
    U = a.proj.U
    # a signal made only of eigenvectors 25..35 lives entirely in the middle band
    P = V + U[:, 25:35] @ np.random.default_rng(0).normal(size=(10, 3))
    low, mid, high = a.split(P)
    assert np.abs(low - V).max() < 1e-10
    assert np.abs(high - V).max() < 1e-10
    assert np.allclose(mid, P, atol=1e-10)


def test_split_sums_back_and_assembly_of_perfect_bands():
    a, V = _fitted(50)
    P = V + np.random.default_rng(1).normal(0, 0.05, V.shape)
    low, high = a.split(P)
    assert np.allclose(low + high - V, P, atol=1e-12)
    assert np.allclose(a.assemble([low, high]), P, atol=1e-12)
    # assembly takes only the low frequencies of the low band and the high of the high band
    noise = np.random.default_rng(2).normal(0, 0.05, V.shape)
    assert np.allclose(a.assemble([low + (noise - a.proj.project(noise, 0, 50)), high]), P, atol=1e-10)


def test_assemble_many_matches_assemble():
    a, V = _fitted(80)
    rng = np.random.default_rng(3)
    lo, hi = V + rng.normal(0, 0.05, V.shape), V + rng.normal(0, 0.05, V.shape)
    # the sphere's eigenvalues repeat (multiplicities 1, 3, 5, ...): cut between multiplets
    many = a.assemble_many([lo, hi], [0, 64, 16])
    for i, k in enumerate([64, 16]):
        b = Spectral(k=k)
        b.fit(Template(V, a_template_faces()), V)
        assert np.allclose(many[i + 1], b.assemble([lo, hi]), atol=1e-8)
    assert np.allclose(many[0], hi)


def a_template_faces():
    return np.asarray(trimesh.creation.icosphere(subdivisions=3).faces)


def test_torch_assembly_matches_numpy():
    torch = pytest.importorskip("torch")
    from fwk_spectral import TorchSpectral

    a, V = _fitted([15, 45])
    rng = np.random.default_rng(4)
    bands = [np.stack([V + rng.normal(0, 0.05, V.shape) for _ in range(2)]) for _ in range(3)]
    ts = TorchSpectral(a, dtype=torch.float64)
    tb = [torch.tensor(b, requires_grad=True) for b in bands]
    out = ts.assemble(tb)
    assert np.allclose(out.detach().numpy(), a.assemble(bands), atol=1e-10)
    out.sum().backward()
    assert tb[0].grad is not None


def test_k_too_large_is_a_clear_error():
    from fwk.errors import RecipeError

    m = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(RecipeError, match="exceeds"):
        Spectral(k=500).fit(Template(m.vertices, m.faces))
