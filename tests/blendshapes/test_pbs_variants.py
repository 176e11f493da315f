"""PBS beyond the thesis (issue 31): the DT anchor (``anchor:``) and the bending term
(``bending_weight:``), each against a naive reference on a small mesh."""
import numpy as np
import pytest
import torch

from fwk.geometry.operators import cotangent_laplacian, mass_matrix
from fwk.runs import make_test_context
from fwk.testing.blendshapes import tiny_blendshape_data

NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
DT = {"name": "dt", "sources": [0, 1]}


@pytest.fixture(scope="module")
def anchored(tmp_path_factory):
    from fwk_pb import PBS

    data = tiny_blendshape_data()
    m = PBS(network=NET, ks=[0, 5, 20, 60, 10_000], anchor=DT)
    m.fit(data, make_test_context(tmp_path_factory.mktemp("anchored"), epochs=1, batch_size=4))
    return m, data


def _dt(data):
    from fwk_dt import DeformationTransfer

    dt = DeformationTransfer(sources=[0, 1])
    dt.fit(data)
    return dt


def _zero_residual(m):
    """Networks replaced by the zero residual: each branch outputs encode(ref, ref) (the
    representation's features of 'no change from the anchor')."""
    def features(N, e, b):
        R = m.refs(N, [e])[e]
        return m.out_reps[b].encode(R, R)

    m.branch_features = features


@pytest.mark.parametrize("expression", ["mouth-wide", "face-compression"])
def test_a_zero_residual_reproduces_deformation_transfer_for_every_k(anchored, expression):
    m, data = anchored
    _zero_residual(m)
    N = np.asarray(data.val.positions[:, 0])
    want = _dt(data).predict(N, expression)
    n = N.shape[1]
    for k in [0, 5, 20, 60, n]:
        got = m.predict(N, expression, k=k)
        # euclidean: exact; dr: the round trip of the identity deformation (float32 features)
        assert np.abs(got - want).max() < 1e-5 * np.abs(want).max(), k


def test_anchored_parts_are_the_anchored_networks_alone(anchored):
    """The part models (the report's single networks) decode against the anchor too: the spatial
    part is PBS at k = n, the dr part PBS at k = 0 (both placed as PBS places them)."""
    m, data = anchored
    m2 = type(m)(network=NET, ks=[0, 5, 20, 60, 10_000], anchor=DT)
    m2.load_state_dict(m.state_dict())
    N = np.asarray(data.val.positions[:, 0])
    parts = list(m2.parts(N, "mouth-wide").values())
    assert np.allclose(parts[0], m2.predict(N, "mouth-wide", k=N.shape[1]), atol=1e-9)
    assert np.allclose(parts[1], m2.single(1).predict(N, "mouth-wide"), atol=1e-9)


def test_anchored_assembly_equals_the_dense_formula(anchored):
    """P'(k) = (I - X_k) P'_diff + X_k P'_spatial with X_k = U_k U_k^T M formed densely from the
    mean neutral's generalised eigenvectors (scipy.linalg.eigh of the dense pencil)."""
    from scipy.linalg import eigh

    m, data = anchored
    N = np.asarray(data.val.positions[:, 0])
    Ps, Pd = m.branches(N, "mouth-wide")
    V, F = m.template.vertices, m.template.triangles
    L = cotangent_laplacian(V, F).toarray()
    M = mass_matrix(V, F).toarray()
    w, U = eigh(-L if np.trace(L) < 0 else L, M)
    for k in [5, 20]:
        X = U[:, :k] @ U[:, :k].T @ M
        want = np.einsum("ij,bjc->bic", np.eye(len(V)) - X, Pd) + np.einsum("ij,bjc->bic", X, Ps)
        got = m.assemble(Ps, Pd, [k])[0]
        assert np.abs(got - want).max() < 1e-6 * np.abs(want).max(), k


def test_anchored_networks_learn_the_residual_from_dt(anchored):
    """The spatial branch's targets are offsets from DT's prediction: encode(P, DT(N))."""
    m, data = anchored
    tr = data.train
    N, P = np.asarray(tr.positions[:, 0]), np.asarray(tr.positions[:, 1])
    e = data.train.shape_names[1]
    A = _dt(data).predict(N, e)
    rep = m.out_reps[0]
    assert np.allclose(rep.decode(rep.encode(P, A), A), P, atol=1e-5)
    assert np.allclose(rep.decode(rep.encode(A, A), A), A, atol=1e-6)  # no residual: DT itself


def test_anchored_state_round_trip_keeps_the_anchor(anchored):
    from fwk_pb import PBS

    m, data = anchored
    N = np.asarray(data.val.positions[:, 0])
    m2 = PBS(network=NET, ks=[0, 5, 20, 60, 10_000], anchor=DT)
    m2.load_state_dict(m.state_dict())
    assert np.array_equal(m2.refs(N, ["mouth-wide"])["mouth-wide"], _dt(data).predict(N, "mouth-wide"))


def test_the_assembler_is_rebuilt_with_the_cut_pbs_kept(anchored):
    """pbs keeps the cut it built its assembler with (``assembler_k``) instead of reading the
    built-in spectral assembler's attributes; a model saved before it kept it reloads from the
    assembler's own record of its cuts. Both predict as the fitted model does."""
    from fwk_pb import PBS

    m, data = anchored  # (other tests of this module patch the fitted model: compare reloads)
    N = np.asarray(data.val.positions[:, 0])
    state = m.state_dict()
    assert state["assembler_k"] == m.assembler_k > 0
    old = {k: v for k, v in state.items() if k != "assembler_k"}
    got = []
    for d in (state, old):
        m2 = PBS(network=NET, ks=[0, 5, 20, 60, 10_000], anchor=DT)
        m2.load_state_dict(d)
        assert m2.assembler_k == m.assembler_k
        got.append(m2.predict(N, "mouth-wide"))
    assert np.isfinite(got[0]).all() and np.array_equal(got[0], got[1])


def test_anchor_must_be_a_blendshape_model():
    from fwk.errors import RecipeError
    from fwk_pb import PBS

    with pytest.raises(RecipeError, match="anchor"):
        PBS(network=NET, anchor="vae")
    # from a recipe: refused when the recipe is validated, naming the full key and the role
    from fwk.recipes import make_spec

    with pytest.raises(RecipeError, match=r"models\.p\.anchor: .*BlendshapeModel"):
        make_spec("model", {"name": "pbs", "network": NET, "anchor": "vae"}, "models.p")


def test_bending_error_equals_a_loop_over_the_cotangent_weights(tmp_path):
    """mean |L D| against L assembled by a loop over triangles (the geometry tests' naive
    cotangent Laplacian; the sign convention does not change |L D|)."""
    from fwk_pb import PBS
    from tests.geometry.test_operators import naive_laplacian

    data = tiny_blendshape_data()
    m = PBS(network=NET, bending_weight=1.0)
    m.template = data.template
    V, F = data.template.vertices, data.template.triangles
    L = naive_laplacian(V, F)
    D = np.random.default_rng(0).normal(size=(3, len(V), 3))
    want = np.mean(np.abs(np.einsum("ij,bjc->bic", L, D)))
    got = float(m.bending_error(torch.as_tensor(D)))
    assert abs(got - want) < 1e-10 * max(want, 1)


def test_bending_weight_enters_the_training_loss(tmp_path):
    """The logged bending term is the spatial branch's |L (output - target)| and training with it
    changes the networks (a weight of 0 logs none)."""
    from fwk_pb import PBS

    data = tiny_blendshape_data()
    with pytest.raises(Exception, match="bending_weight"):
        PBS(network=NET, bending_weight=float("nan"))
    a = PBS(network=NET, ks=[0, 10_000], k=0)
    a.fit(data, make_test_context(tmp_path / "a", epochs=2, batch_size=4))
    b = PBS(network=NET, ks=[0, 10_000], k=0, bending_weight=1.0)
    b.fit(data, make_test_context(tmp_path / "b", epochs=2, batch_size=4))
    N = np.asarray(data.val.positions[:, 0])
    Fa, Fb = a.branch_features(N, "mouth-wide", 0), b.branch_features(N, "mouth-wide", 0)
    assert not np.allclose(Fa, Fb)
    # the differential branch's loss has no bending term: its gradient path is untouched by the weight


def test_a_conditional_anchored_pbs_predicts_every_expression_from_the_anchor(tmp_path):
    """The rig's conditional PBS with an anchor: predict_all (one encoder pass, every expression's
    condition decoded in batches) equals one expression at a time, and a zero residual gives DT
    for every expression."""
    from fwk_pb import PBS

    data = tiny_blendshape_data()
    m = PBS(network=NET, ks=[0, 20, 10_000], anchor=DT, conditional=True)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    N = np.asarray(data.val.positions[:, 0])
    es = list(m.expressions)
    many = m.predict_all(N, es)
    for e in es:
        assert np.allclose(many[e], m.predict(N, e), atol=1e-5)
    m.branch_features_many = lambda N_, exprs, b, batch=64: {
        e: m.out_reps[b].encode(m.refs(N_, [e])[e], m.refs(N_, [e])[e]) for e in exprs}
    zero = m.predict_all(N, es)
    want = _dt(data).predict_all(N, es)
    for e in es:
        assert np.abs(zero[e] - want[e]).max() < 1e-5 * np.abs(want[e]).max(), e
