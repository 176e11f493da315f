import numpy as np
import pytest

from fwk.data.preprocess import Preprocessor
from fwk.protocols import FitData
from fwk.runs import make_test_context

NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}


def _data(n_subjects=10, n_vertices=300):
    from fwk.plugins import get_registry

    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=n_vertices,
                                                            shapes=["neutral", "mouth-wide"]).load(None)
    tr = n_subjects - 3
    pre = Preprocessor().fit(np.asarray(col.positions[:tr, 0]), np.asarray(col.positions[:tr]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    return FitData(col.template.with_vertices(pre.mean_neutral), col.select(np.arange(tr)),
                   col.select(np.arange(tr, n_subjects)), ["neutral", "mouth-wide"])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from fwk_pb import PBS

    data = _data()
    ctx = make_test_context(tmp_path_factory.mktemp("pbs"), epochs=1, batch_size=4)
    m = PBS(network=NET, ks=[0, 5, 20, 60, 10_000])
    m.fit(data, ctx)
    return m, data


def _perfect(m, data):
    """Replace the networks by the ground truth: branch_features returns encode(GT)."""
    va = data.val
    N, G = np.asarray(va.positions[:, 0]), np.asarray(va.positions[:, 1])

    def features(N_, e, b):
        assert np.allclose(N_, N)
        return m.out_reps[b].encode(G, N)

    m.branch_features = features
    return N, G


def test_perfect_networks_give_the_ground_truth_for_every_k_exactly(tmp_path):
    """With two exactly invertible representations (euclidean std and norm), feeding the
    ground truth through decode and eq. 5.10 returns it for every k."""
    from fwk_pb import PBS

    data = _data()
    m = PBS(spatial={"name": "euclidean", "scaling": "std"}, differential={"name": "euclidean", "scaling": "norm"},
            network=NET, ks=[0, 1, 7, 30, 100, 299, 10_000], k=1)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    N, G = _perfect(m, data)
    for k in [0, 1, 7, 30, 100, 299, G.shape[1]]:
        assert np.abs(m.predict(N, "mouth-wide", k=k) - G).max() < 1e-6, k  # float32 features


def test_perfect_networks_with_dr_reproduce_the_ground_truth_up_to_the_dr_round_trip(trained):
    m, data = trained
    m2 = type(m)(network=NET)
    m2.load_state_dict(m.state_dict())
    N, G = _perfect(m2, data)
    n = G.shape[1]
    P0 = m2.predict(N, "mouth-wide", k=0)
    dr = m2.out_reps[1]
    assert np.allclose(P0, dr.decode(dr.encode(G, N), N, target=G), atol=1e-6)  # the dr round trip alone
    err0 = np.abs(P0 - G).max()
    assert np.abs(P0 - G).mean() < 5e-3 * np.abs(G).max()
    assert np.abs(m2.predict(N, "mouth-wide", k=n) - G).max() < 1e-6  # float32 features
    for k in [1, 5, 20, 60]:
        err = np.abs(m2.predict(N, "mouth-wide", k=k) - G).max()
        assert err <= 2 * err0 + 1e-9, k
    # P'(k) - G = (I - X_k)(P_diff - G), an M-orthogonal projection: its M-norm never grows with k
    Mw = m2.assembler.proj.m
    errs = [float((Mw[None, :, None] * (m2.predict(N, "mouth-wide", k=k) - G) ** 2).sum()) for k in (0, 5, 20, 60)]
    assert all(b <= a + 1e-12 for a, b in zip(errs, errs[1:])) and errs[-1] < errs[0]


def test_parts_equal_the_single_pb_predictions(trained):
    m, data = trained
    N = np.asarray(data.val.positions[:, 0])
    n = N.shape[1]
    spatial, diff = m.single(0), m.single(1)
    Ps = spatial.predict(N, "mouth-wide")
    assert np.allclose(m.predict(N, "mouth-wide", k=n), Ps, atol=1e-12)
    assert np.allclose(m.predict(N, "mouth-wide", k=0), diff.predict(N, "mouth-wide", target=Ps), atol=1e-12)
    ends = m.parts(N, "mouth-wide")
    assert np.allclose(ends["pb-euclidean-std"], Ps)
    # in between, eq. 5.10 against a direct evaluation with the explicit basis
    k = 20
    Pd = diff.predict(N, "mouth-wide", target=Ps)
    U, Mdiag = m.assembler.proj.U[:, :k], m.assembler.proj.m
    X = U @ (U.T * Mdiag[None])
    expect = np.einsum("ij,bjc->bic", np.eye(n) - X, Pd) + np.einsum("ij,bjc->bic", X, Ps)
    assert np.allclose(m.predict(N, "mouth-wide", k=k), expect, atol=1e-9)


def test_k_is_chosen_on_the_front_and_saved(trained):
    m, data = trained
    s = m.sweep["mouth-wide"]
    assert m.k["mouth-wide"] in s["front_fmpd"]
    assert len(s["ks"]) == len(s["l1"]) == len(s["dame"]) == len(s["fmpd"])
    m2 = type(m)(network=NET)
    m2.load_state_dict(m.state_dict())
    N = np.asarray(data.val.positions[:, 0])
    assert m2.k == m.k
    assert np.allclose(m2.predict(N, "mouth-wide"), m.predict(N, "mouth-wide"), atol=1e-6)


def test_thesis_ks_and_knee():
    from fwk_pb import knee, thesis_ks

    printed = [*range(0, 101, 10), 120, 140, 160, 180, 200, *range(230, 471, 30), *range(500, 1001, 50)]
    assert len(printed) == 36  # thesis 5.3.4: |K| = 37 with n
    for n in (14921, 11248, 1001):  # the grid as printed, whatever n (no rescaling by n / 14,921)
        assert thesis_ks(n) == [*printed, n]
    assert 440 in thesis_ks(11248) and 380 in thesis_ks(11248)  # the thesis's chosen k are on it
    # a small template: values >= n clamp to n and collapse onto it
    assert thesis_ks(500) == [k for k in printed if k < 500] + [500]
    assert thesis_ks(250) == [k for k in printed if k < 250] + [250]
    assert thesis_ks(1000) == printed
    # an L-shaped front: the corner is the knee
    x = np.array([0.0, 0.1, 0.2, 1.0])
    y = np.array([1.0, 0.2, 0.1, 0.0])
    assert knee(x, y) == 1
    assert knee(x[::-1], y[::-1]) == 2
    # two points: the smaller relative excess (2 + 1 against 1 + 10)
    assert knee(np.array([2.0, 1.0]), np.array([1.0, 10.0])) == 0


def test_two_step_and_conditional_train_and_reload(tmp_path):
    from fwk_pb import PB, PBS

    data = _data(8, 250)
    N = np.asarray(data.val.positions[:, 0])
    for cls, kw in [(PB, {"mode": "two-step", "representation": "dr"}), (PBS, {"conditional": True, "k": 10})]:
        m = cls(network=NET, **kw)
        m.fit(data, make_test_context(tmp_path / cls.name, epochs=1, batch_size=4))
        P = m.predict(N, "mouth-wide")
        assert P.shape == N.shape and np.all(np.isfinite(P))
        m2 = cls(network=NET, **kw)
        m2.load_state_dict(m.state_dict())
        assert np.allclose(m2.predict(N, "mouth-wide"), P, atol=1e-6)


def test_two_step_freezes_the_neutral_encoder(tmp_path):
    from fwk_pb import PB

    data = _data(8, 250)
    m = PB(network=NET, mode="two-step")
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    assert all(not p.requires_grad for p in m.nets["b0"].enc.parameters())
    assert any(p.requires_grad for p in m.nets["b0"].dec.parameters())


def _data3(n_subjects=8, n_vertices=250):
    """Like _data with all three synthetic expressions."""
    from fwk.plugins import get_registry

    shapes = ["neutral", "face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"]
    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=n_vertices,
                                                            shapes=shapes).load(None)
    tr = n_subjects - 3
    pre = Preprocessor().fit(np.asarray(col.positions[:tr, 0]), np.asarray(col.positions[:tr]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    return FitData(col.template.with_vertices(pre.mean_neutral), col.select(np.arange(tr)),
                   col.select(np.arange(tr, n_subjects)), shapes)


def test_conditional_predict_all_batched_equals_one_expression_at_a_time(tmp_path):
    """A conditional model's predict_all decodes every expression in one batch (fwk apply's
    speed); it equals predict one expression at a time (the reference) to float32 rounding, for
    PBS (both branches, dr placed, assembled at each k) and for a dr PB with a target."""
    from fwk_pb import PB, PBS

    data = _data3()
    exprs = ["face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"]
    N = np.asarray(data.val.positions[:, 0])
    G = {e: np.asarray(data.val.positions[:, j]) for j, e in enumerate(exprs, start=1)}
    for cls, kw in [(PBS, {"conditional": True, "k": {"face-compression": 0, "mouth-wide": 30}}),
                    (PB, {"conditional": True, "representation": "dr"})]:
        m = cls(network=NET, **kw)
        m.fit(data, make_test_context(tmp_path / cls.name, epochs=1, batch_size=4))
        target = G if cls is PB else None
        batched = m.predict_all(N, exprs, target)
        assert list(batched) == exprs
        for e in exprs:
            one = m.predict(N, e, G[e] if cls is PB else None)
            assert batched[e].shape == N.shape
            assert np.abs(batched[e] - one).max() < 1e-5, (cls.name, e)
        # the expressions differ from each other (the condition reached the decoder)
        assert not np.allclose(batched["mouth-wide"], batched["face-compression"], atol=1e-4)
        # decoder batches smaller than the expressions: the same values
        F1 = m.branch_features_many(N, exprs, 0, batch=1)
        F64 = m.branch_features_many(N, exprs, 0)
        for e in exprs:
            assert np.allclose(F1[e], F64[e], atol=1e-5)


def test_pairs_equal_a_loop_over_present_subject_expression_pairs():
    """A conditional model trains on (subject, expression) pairs: one sample per present pair,
    subject-major, the subject's inputs beside the pair's target (naive loop as reference)."""
    import torch

    from fwk_pb import _pairs

    rng = np.random.default_rng(0)
    S, E, B = 5, 3, 2
    X = [torch.as_tensor(rng.normal(size=(S, 7, 3 + 6 * b))) for b in range(B)]
    Y = [torch.as_tensor(rng.normal(size=(S, 7, 3 + 6 * b))) for b in range(B) for _ in range(E)]
    mask = torch.as_tensor(rng.random((S, E)) > 0.3)
    out = _pairs(X, Y, mask)
    ref = [(s, e) for s in range(S) for e in range(E) if mask[s, e]]
    assert out[-1].tolist() == [e for _, e in ref]
    for b in range(B):
        assert torch.equal(out[b], torch.stack([X[b][s] for s, _ in ref]))
        assert torch.equal(out[B + b], torch.stack([Y[b * E + e][s] for s, e in ref]))


def test_conditional_loss_is_the_mean_over_pairs_each_with_its_own_condition(tmp_path):
    """The conditional training loss on a batch of pairs equals, per network, the L1 of each pair
    decoded alone with its own expression's one-hot (the per-expression decode path), averaged
    over the pairs (in eval mode: latent means, no sampling; KL weight 0)."""
    import torch

    from fwk_pb import PBS, _conditional_module, _pairs

    data = _data3()
    m = PBS(network=NET, conditional=True, k=10)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    tr = data.train
    E = len(m.expressions)
    X = [torch.as_tensor(r.encode(np.asarray(tr.positions[:, 0]))) for r in m.in_reps]
    N = np.asarray(tr.positions[:, 0])
    Y = [torch.as_tensor(m.expr_scalers[b][i].transform(
        m.out_reps[b].encode(np.asarray(tr.positions[:, tr.shape_index(e)]), N)).astype(np.float32))
         for b in range(2) for i, e in enumerate(m.expressions)]
    batch = _pairs(X, Y, torch.ones(len(N), E, dtype=torch.bool))
    module = _conditional_module(m, 0.0, "t")
    module.eval()
    module.log = lambda *a, **k: None
    with torch.no_grad():
        got = float(module.loss(batch, "val"))
    want = 0.0
    with torch.no_grad():
        for b in range(2):
            def un(e, T):  # the expression's own scaler, then the representation's: one pair at a time
                return m.out_reps[b].unscale(m.expr_scalers[b][e].inverse_torch(T))

            errs = []
            for s in range(len(N)):
                for e in range(E):
                    zs, _ = m._latent(b, X[b][s:s + 1], sample=False)
                    errs.append(torch.abs(un(e, m._decode(b, e, zs)) - un(e, Y[b * E + e][s:s + 1])).mean())
            want += float(torch.stack(errs).mean())
    assert abs(got - want) < 1e-5 * want


def test_conditional_training_decodes_batch_size_pairs_per_step(tmp_path):
    """Memory of a conditional step is bounded by batch_size decodes, not batch_size x the number
    of expressions (57 ICT-FaceKit expressions x 16 subjects took over 22 GB at 11,248 vertices)."""
    from fwk_pb import PBS

    data = _data3(n_subjects=9)
    m = PBS(network=NET, conditional=True, k=10)
    events = []  # (branch, "enc" | "dec", batch size) in call order during fit
    orig = m._make_nets

    def make_nets(*a, **k):
        orig(*a, **k)
        for b in range(2):
            for part in ("enc", "dec"):
                getattr(m.nets[f"b{b}"], part).register_forward_hook(
                    lambda mod, inp, out, b=b, part=part: events.append((b, part, len(inp[0]))))

    m._make_nets = make_nets
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    pairs = len(data.train.positions) * 3
    for b in range(2):
        per_code = []  # samples decoded from each encoder pass (one step's graph)
        for bb, part, n in events:
            if bb != b:
                continue
            if part == "enc":
                per_code.append(0)
            else:
                per_code[-1] += n
        assert len(per_code) >= pairs / 4 and max(per_code) <= 4, per_code


@pytest.mark.parametrize("rep", [{"name": "euclidean", "scaling": "std"}, {"name": "dr", "scaling": "norm"}])
def test_targets_are_scaled_per_expression_as_a_representation_fitted_on_it_alone(tmp_path, rep):
    """Thesis 5.2.1: the network of expression n sees g fitted on that expression's training
    subjects. fwk fits the representation on all expressions and re-scales per expression; the
    features equal those of a representation fitted on the expression alone, and decoding them
    back gives the mesh."""
    import torch

    from fwk_pb import PB, _build_rep
    from fwk.recipes import make_spec

    data = _data3()
    m = PB(representation=rep, network=NET)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    tr, va = data.train, data.val
    N, Nv = np.asarray(tr.positions[:, 0]), np.asarray(va.positions[:, 0])
    for i, e in enumerate(m.expressions):
        P, Pv = np.asarray(tr.positions[:, tr.shape_index(e)]), np.asarray(va.positions[:, va.shape_index(e)])
        alone = _build_rep(make_spec("representation", rep, "representation"))
        alone.fit(P, N, data.template)
        ours = m.expr_scalers[0][i].transform(m.out_reps[0].encode(Pv, Nv))
        # equal up to the float32 rounding of the pooled features, compared in the representation's
        # own units (where the loss is): divided by a per-expression spread much smaller than the
        # pool's, that rounding grows in the scaled units
        assert np.abs((ours - alone.encode(Pv, Nv)) * alone.scaler.div).max() < 1e-6, e
        back = m.out_reps[0].decode(m.expr_inverse(0, i, torch.as_tensor(ours)).numpy(), Nv, Pv)
        # the representation's own round trip (dr integrates in the least-squares sense: not exact)
        assert np.abs(back - m.out_reps[0].decode(m.out_reps[0].encode(Pv, Nv), Nv, Pv)).max() < 1e-5


def test_a_zero_network_output_is_the_expressions_mean_offset(tmp_path):
    """With the per-expression scaling the decoders start from each expression's mean training
    offset (a small expression is not drowned by a large one): zero features decode to the
    neutral plus that expression's mean offset, different per expression."""
    import torch

    from fwk_pb import PB

    data = _data3()
    m = PB(representation={"name": "euclidean", "scaling": "std"}, network=NET, conditional=True)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    tr = data.train
    N = np.asarray(tr.positions[:, 0])
    Nv = np.asarray(data.val.positions[:, 0])
    for i, e in enumerate(m.expressions):
        mean_offset = (np.asarray(tr.positions[:, tr.shape_index(e)]) - N).mean(0)
        F = m.expr_inverse(0, i, torch.zeros(len(Nv), N.shape[1], 3)).numpy()
        assert np.allclose(m.out_reps[0].decode(F, Nv), Nv + mean_offset, atol=1e-6), e
    # per-sample indices (a conditional batch) gather the same scalers as one index at a time
    G = torch.randn(6, N.shape[1], 3)
    e = torch.tensor([0, 2, 1, 1, 0, 2])
    want = torch.stack([m.expr_inverse(0, int(j), G[s:s + 1])[0] for s, j in enumerate(e)])
    assert torch.allclose(m.expr_inverse(0, e, G), want, atol=1e-6)


def test_a_model_saved_before_the_per_expression_scaling_loads_with_one_scaling(tmp_path):
    from fwk_pb import PB

    data = _data3()
    m = PB(representation={"name": "euclidean", "scaling": "std"}, network=NET)
    m.fit(data, make_test_context(tmp_path, epochs=1, batch_size=4))
    state = m.state_dict()
    assert len(state["expr_scalers"][0]) == len(m.expressions)
    del state["expr_scalers"]
    old = PB(representation={"name": "euclidean", "scaling": "std"}, network=NET)
    old.load_state_dict(state)
    assert old.expr_scalers is None
    N = np.asarray(data.val.positions[:, 0])
    e = m.expressions[0]
    F = old.branch_features(N, e, 0)  # the network's output taken as pooled features, as it was trained
    assert np.allclose(old.predict(N, e), old.out_reps[0].decode(F, N))
