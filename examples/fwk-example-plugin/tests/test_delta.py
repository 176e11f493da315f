"""The example representation passes fwk's representation contract suite (absolute and
relative), matches a dense loop-built Laplacian and a dense least-squares solve, round-trips to
1e-8 with its anchors, and trains inside ae from a recipe."""
import numpy as np
import pytest

from fwk.errors import RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.testing.representation import RepresentationContract
from fwk.testing.sampler import two_components
from fwk_example_plugin.delta import Delta
from recipe_runs import assert_tested, run_recipe, tiny_recipe


class TestDeltaContract(RepresentationContract):
    component = Delta


class TestDeltaRelativeNormContract(RepresentationContract):
    component = Delta
    params = {"relative": True, "scaling": "norm", "granularity": "vertex"}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("representation", "delta")
    assert e.component is Delta and e.plugin == "example-delta"


def batch(t, b=5, seed=0):
    """(b, n, 3) smooth random deformations of the template t (scaled, bent, noisy, moved)."""
    rng = np.random.default_rng(seed)
    V = t.vertices
    out = []
    for _ in range(b):
        X = V * (1 + 0.1 * rng.normal(size=3)) + 0.05 * np.sin(V[:, [1, 2, 0]] * rng.normal(size=3))
        out.append(X + rng.normal(0, 0.01, V.shape) + rng.normal(size=3))
    return np.stack(out)


def dense_laplacian(t):
    """L = I - D^-1 A built by a loop over the triangles' edges."""
    n = t.n_vertices
    nbrs = [set() for _ in range(n)]
    for f in t.triangles:
        for a in range(3):
            for b in range(3):
                if a != b:
                    nbrs[f[a]].add(int(f[b]))
    L = np.eye(n)
    for i in range(n):
        for j in nbrs[i]:
            L[i, j] -= 1.0 / len(nbrs[i])
    return L


def test_encode_is_a_dense_loop_built_laplacian_times_p():
    t = two_components()
    P = batch(t)
    r = Delta(scaling="none")
    r.fit(P, None, t)
    L = dense_laplacian(t)
    want = np.einsum("ij,bjc->bic", L, P)
    assert np.allclose(r.raw_features(P), want, atol=1e-12)
    assert np.allclose(r.encode(P), want.astype(np.float32), atol=1e-5)
    assert np.abs(want.sum(axis=(0, 2))).max() > 0  # not trivially zero


def test_round_trip_to_1e8_with_one_anchor_per_component():
    t = two_components()  # two connected components: two anchors
    P = batch(t)
    r = Delta(scaling="none")
    r.fit(P, None, t)
    a = r.anchor_index
    labels = t.components
    assert len(a) == 2 and sorted(labels[a]) == [0, 1]
    for c, v in zip(labels[a], a):  # each anchor is the vertex nearest its component's centroid
        idx = np.flatnonzero(labels == c)
        assert v == idx[np.argmin(np.linalg.norm(r.mean[idx] - r.mean[idx].mean(0), axis=1))]
    D = r.raw_features(P)
    X = r.integrate(D, None, P)  # placed onto the ground truth
    assert np.abs(X - P).max() < 1e-8
    X0 = r.integrate(D)  # without a target: the anchors sit on the fitted mean ...
    assert np.abs(X0[:, a] - r.mean[a]).max() < 1e-8
    for c in (0, 1):  # ... and each component is P moved by one translation
        m = labels == c
        shift = X0[:, m] - P[:, m]
        assert np.abs(shift - shift[:, :1]).max() < 1e-8
    assert np.abs(r.decode(r.encode(P), None, P) - P).max() < 1e-5  # float32 features
    assert np.array_equal(r.encode(P[1]), r.encode(P)[1])  # one (n, 3) mesh as a batch of one
    assert np.allclose(r.decode(r.encode(P[1]), None, P[1]), P[1], atol=1e-5)


def test_decode_is_the_dense_anchored_least_squares_solution():
    t = two_components()
    P = batch(t, b=2)
    w = 0.5
    r = Delta(scaling="none", anchors=3, anchor_weight=w)
    r.fit(P, None, t)
    a = r.anchor_index
    assert len(a) == 6
    L = dense_laplacian(t)
    S = np.zeros((len(a), t.n_vertices))
    S[np.arange(len(a)), a] = 1.0
    delta = np.random.default_rng(3).normal(size=(2, t.n_vertices, 3))  # not in the range of L
    X = r.integrate(delta)
    for s in range(2):
        A = np.vstack([L, w * S])
        B = np.vstack([delta[s], w * r.mean[a]])
        want = np.linalg.lstsq(A, B, rcond=None)[0]
        assert np.abs(X[s] - want).max() < 1e-8 * max(1.0, np.abs(want).max())


def test_relative_holds_the_anchors_at_each_reference():
    t = two_components()
    P, R = batch(t, seed=1), batch(t, seed=2)
    r = Delta(relative=True)
    r.fit(P, R, t)
    F = r.encode(P, R)
    assert F.shape == P.shape and F.dtype == np.float32
    Dr = r.raw_features(P, R)
    L = dense_laplacian(t)
    assert np.allclose(Dr, np.einsum("ij,bjc->bic", L, P - R), atol=1e-12)
    X0 = r.integrate(Dr, R)
    assert np.abs(X0[:, r.anchor_index] - R[:, r.anchor_index]).max() < 1e-8
    assert np.abs(r.integrate(Dr, R, P) - P).max() < 1e-8
    shared = r.encode(P, R[0])  # a shared (n, 3) reference broadcasts
    assert np.allclose(shared, r.encode(P, np.broadcast_to(R[0], P.shape)))


@pytest.mark.parametrize("params, words", [({"anchors": 0}, "anchors"), ({"anchor_weight": 0.0}, "anchor_weight"),
                                           ({"scaling": "whiten"}, "scaling"), ({"relative": "yes"}, "relative")])
def test_bad_parameters_are_recipe_errors(params, words):
    with pytest.raises(RecipeError, match=words):
        Delta(**params)


RECIPE = tiny_recipe("""
ae-delta: {name: ae, conv: {name: cheb, k: 3}, channels: [8, 16], latent: 8,
           sampler: {name: quadric, factors: [4, 4]}, representation: {name: delta, anchors: 1}}
""", kl_weight=None)


def test_delta_trains_as_an_ae_representation(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "delta.yaml", RECIPE, monkeypatch)
    assert_tested(run_dir, ["ae-delta"])
    model = open_run(run_dir).model("ae-delta")  # the representation's state reopens from the run
    assert isinstance(model.rep, Delta) and model.rep.anchor_index is not None
    S = model.sample(2, seed=0)  # decoded without a target: placed by the anchors
    assert S.shape[0] == 2 and np.isfinite(S).all()
