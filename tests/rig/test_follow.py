"""Followers (fwk.rig.follow): the parts of a full mesh outside a model's region move with the
predicted face. Synthetic: a naive loop reference of G, the anchors and the amplitude; exact
multiples reproduced; an expression that moves nothing outside stores nothing; rigid motion and
scale of the input head. ICT-FaceKit: a tiny blendshapes run with ``follow: {region: full}``
applied to a test subject's full head (skipped without the data)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fwk.data.preprocess import Preprocessor
from fwk.errors import DataError
from fwk.rig.follow import A_MAX, ANCHOR_MIN, ANCHORS, NEGLIGIBLE, Followers, follow, outside_parts
from fwk.safeio import load_npz
from fwk.testing import ICT_SKIP_REASON, ict_path

N_GRID = 10  # region: an N_GRID x N_GRID vertex grid


def _mesh(rng):
    """(vertices, triangles, n): a bumpy grid region, then three outside parts (two triangle
    strips below the grid and a lone triangle far off); one triangle joins a strip to the grid."""
    x, y = np.meshgrid(np.linspace(-1, 1, N_GRID), np.linspace(-1, 1, N_GRID))
    V = [np.stack([x.ravel(), y.ravel(), 0.1 * rng.standard_normal(x.size)], 1)]
    F = []
    for j in range(N_GRID - 1):
        for i in range(N_GRID - 1):
            a = j * N_GRID + i
            F += [[a, a + 1, a + N_GRID], [a + 1, a + N_GRID + 1, a + N_GRID]]
    n = N_GRID * N_GRID
    k = n
    for off in (-0.5, 0.5):  # two strips of 6 vertices under the grid's lower half
        s = np.array([[off + 0.1 * (i // 2), -0.6 + 0.1 * (i % 2), -0.3] for i in range(6)])
        V.append(s)
        F += [[k + i, k + i + 1, k + i + 2] for i in range(4)]
        k += 6
    V.append(np.array([[5.0, 5.0, 5.0], [5.1, 5.0, 5.0], [5.0, 5.1, 5.0]]))  # far away: no anchors
    F.append([k, k + 1, k + 2])
    F.append([0, 1, n])  # a polygon joining region and outside does not join outside parts
    return np.concatenate(V), np.array(F), n


def _edges(F):
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _data(rng, V, n, S=6):
    """Registered neutrals and deltas per expression: ``jaw`` moves the lower grid and the two
    strips (amplitude c_s per subject), ``far`` moves only the far triangle, ``face`` only the
    region's upper half."""
    N = V[None] + 0.01 * rng.standard_normal((S, *V.shape))
    c = 1.0 + 0.2 * rng.standard_normal(S)
    base = np.zeros_like(V)
    base[:n, 1] = -np.clip(-V[:n, 1], 0, None)  # lower half of the grid moves down
    base[n:n + 12, 1] = -0.7
    base[n:n + 12, 2] = 0.1 * np.arange(12) / 12
    jaw = c[:, None, None] * base[None]
    far = np.zeros((S, *V.shape))
    far[:, n + 12:, 0] = 0.3 * (1 + 0.1 * rng.standard_normal((S, 1)))
    face = np.zeros((S, *V.shape))
    face[:, :n, 2] = 0.2 * np.clip(V[:n, 1], 0, None)[None] * c[:, None]
    return N, {"jaw": jaw, "far": far, "face": face}, c


def _naive(V, F, n, deltas):
    """Plain loops: parts by flood fill, G, the anchors and nothing else."""
    n_full = len(V)
    nb = {v: set() for v in range(n, n_full)}
    for t in F:
        for a in t:
            for b in t:
                if a != b and a >= n and b >= n:
                    nb[a].add(b)
    part, parts = {}, []
    for v in range(n, n_full):
        if v in part:
            continue
        stack, comp = [v], []
        part[v] = len(parts)
        while stack:
            u = stack.pop()
            comp.append(u)
            for w in nb[u]:
                if w not in part:
                    part[w] = len(parts)
                    stack.append(w)
        parts.append(sorted(comp))
    out = {}
    for e, D in deltas.items():
        G = [sum(D[s][v] for s in range(len(D))) / len(D) for v in range(n_full)]
        top = max(float(np.sqrt(sum(x * x for x in g))) for g in G)
        for p, comp in enumerate(parts):
            peak = max(float(np.sqrt(sum(x * x for x in G[v]))) for v in comp)
            if peak < NEGLIGIBLE * top:
                continue
            cand = []
            for u in range(n):
                if np.sqrt(sum(x * x for x in G[u])) >= ANCHOR_MIN * peak:
                    d = min(float(np.sqrt(sum((V[u][k] - V[v][k]) ** 2 for k in range(3)))) for v in comp)
                    cand.append((d, u))
            cand.sort()
            A = [u for _, u in cand[:ANCHORS]]
            out[(e, p)] = (comp, np.array([G[v] for v in comp]), A, np.array([G[u] for u in A]).reshape(-1, 3))
    return out


def test_parts_g_and_anchors_match_a_naive_loop():
    rng = np.random.default_rng(0)
    V, F, n = _mesh(rng)
    N, deltas, _ = _data(rng, V, n)
    M = N.mean(0)
    f = Followers.fit(_edges(F), n, M, deltas, list(deltas))
    ref = _naive(M, F, n, deltas)
    lab = outside_parts(_edges(F), n, len(V))
    assert lab.max() + 1 == 3 and list(np.bincount(lab)) == [6, 6, 3]
    got = {}
    for e in deltas:
        for p, G, A, GA in f.entries(e):
            got[(e, p)] = (list(np.flatnonzero(lab == p) + n), G, list(A), GA)
    assert set(got) == set(ref) == {("jaw", 0), ("jaw", 1), ("far", 2)}
    for key, (comp, G, A, GA) in ref.items():
        assert got[key][0] == comp
        assert np.allclose(got[key][1], G)
        assert set(got[key][2]) == set(A), key  # ties in distance may order differently
        assert np.allclose(got[key][3][np.argsort(got[key][2])], GA[np.argsort(A)])
    # the amplitude of a naive least squares on the anchors
    D = deltas["jaw"][2, :n]
    X = N[2, :n]
    comp, G, A, GA = ref[("jaw", 0)]
    a = sum(float(D[u] @ GA[i]) for i, u in enumerate(A)) / float((GA * GA).sum())
    out = f.deltas(X, D, "jaw")
    assert np.allclose(out[np.array(comp) - n], a * G)
    assert np.allclose(out[12:], 0.0)  # the far part does not move for jaw


def test_exact_multiple_reproduced_and_nothing_stored():
    rng = np.random.default_rng(1)
    V, F, n = _mesh(rng)
    N, deltas, c = _data(rng, V, n)
    f = Followers.fit(_edges(F), n, N.mean(0), deltas, list(deltas))
    assert f.summary() == {"jaw": 2, "far": 1}  # face moves no outside vertex: nothing stored
    assert list(f.entries("face")) == []
    assert np.all(f.deltas(N[0, :n], deltas["face"][0, :n], "face") == 0)
    # a subject whose delta is exactly c * G everywhere is reproduced with a = c
    G = deltas["jaw"].mean(0)
    for k in (0.5, 1.0, 1.7):
        out = f.deltas(N[0, :n], k * G[:n], "jaw")
        assert np.allclose(out[:12], k * G[n:n + 12], atol=1e-12)
    # clipped at A_MAX
    assert np.allclose(f.deltas(N[0, :n], 10 * G[:n], "jaw")[:12], A_MAX * G[n:n + 12])
    # without anchors (the far part): a = rho, the head's size over the mean's (1 at the mean's size)
    M = N.mean(0)
    far = f.deltas(M[:n], np.zeros((n, 3)), "far")
    assert np.allclose(far[12:], deltas["far"].mean(0)[n + 12:])
    assert np.allclose(f.deltas(2 * M[:n], np.zeros((n, 3)), "far")[12:], 2 * deltas["far"].mean(0)[n + 12:])


def test_state_round_trip_and_damaged_state(tmp_path):
    rng = np.random.default_rng(2)
    V, F, n = _mesh(rng)
    N, deltas, _ = _data(rng, V, n)
    f = Followers.fit(_edges(F), n, N.mean(0), deltas, list(deltas))
    np.savez(tmp_path / "f.npz", **f.state_dict())
    g = Followers.from_state(load_npz(tmp_path / "f.npz"))
    for e in deltas:
        assert np.array_equal(g.deltas(N[1, :n], deltas[e][1, :n], e), f.deltas(N[1, :n], deltas[e][1, :n], e))
    bad = dict(f.state_dict(), anchors=f.anchors + 1000)
    with pytest.raises(DataError, match="x.npz: .*inconsistent"):
        Followers.from_state(bad, "x.npz")
    with pytest.raises(DataError, match="x.npz: not the followers"):
        Followers.from_state({"n": 3}, "x.npz")


def _rotation(rng):
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return Q * np.sign(np.linalg.det(Q))


def test_rigid_motion_and_scale_of_the_input_head():
    """Everything through the preprocessing: a rotated, translated and scaled head (its predicted
    region moved alike) gives the same full expressions moved and scaled."""
    rng = np.random.default_rng(3)
    V, F, n = _mesh(rng)
    N, deltas, _ = _data(rng, V, n)
    # input-frame subjects: each rotated and moved; the preprocessing registers them
    Qs = [_rotation(rng) for _ in N]
    raw = np.stack([Ni @ Q.T + rng.standard_normal(3) for Ni, Q in zip(N, Qs)])
    raw_jaw = np.stack([(Ni + Di) @ Q.T + (r[0] - Ni[0] @ Q.T) for Ni, Di, Q, r in zip(N, deltas["jaw"], Qs, raw)])
    pre = Preprocessor().fit(raw[:, :n])
    X, T = pre.transform_neutrals(raw[:, :n])
    Xf = pre.apply(raw, T)
    Df = pre.apply(raw_jaw, T) - Xf
    f = Followers.fit(_edges(F), n, Xf.mean(0), {"jaw": Df}, ["jaw"])
    head, pred = raw[0], raw_jaw[0, :n] + 0.01 * rng.standard_normal((n, 3))
    base = follow(pre, f, head, {"jaw": pred})["jaw"]
    assert not np.allclose(base[n:n + 12], head[n:n + 12])  # the strips moved
    assert np.allclose(base[n + 12:], head[n + 12:])  # the far part did not
    Q, t, k = _rotation(rng), np.array([3.0, -2.0, 7.0]), 1.3
    moved = follow(pre, f, k * head @ Q.T + t, {"jaw": k * pred @ Q.T + t})["jaw"]
    assert np.allclose(moved, k * base @ Q.T + t, atol=1e-9)


def test_fit_refuses_a_mesh_without_outside():
    with pytest.raises(DataError, match="nothing outside"):
        Followers.fit(np.array([[0, 1]]), 2, np.zeros((2, 3)), {}, [])


# ---------------------------------------------------------------------- ICT-FaceKit
ICT = ict_path()
#: ICT-FaceKit's published vertex ranges (github.com/ICT-VGL/ICT-FaceKit, README "Model details"):
#: teeth 17039-21450 (upper and lower), eyeball left 21451-23020, eyelashes 25351-26718
TEETH = (17039, 21451)
EYEBALL_L = (21451, 23021)
EYELASHES = (25351, 26719)
N_REGION = 11248


@pytest.fixture(scope="module")
def ict_run(tmp_path_factory):
    if ICT is None:
        pytest.skip(ICT_SKIP_REASON)
    from .conftest import _execute

    tmp = tmp_path_factory.mktemp("ict-follow")
    recipe = {"name": "ict-follow", "task": "blendshapes", "seed": 0,
              "dataset": {"name": "ict-facekit", "path": str(ICT), "region": "face-head", "n_subjects": 10,
                          "shapes": ["neutral", "jawOpen", "eyeLookDown_L"]},
              "follow": {"region": "full"}, "split": {"ratios": [0.6, 0.2, 0.2]},
              "models": {"dt": {"name": "dt", "sources": 0}}, "renders": 0, "metrics": ["l1", "l2"]}
    return _execute(recipe, tmp), tmp


def test_ict_full_head_follows(ict_run):
    """A test subject's full head through ``fwk apply``: the lower teeth (the teeth vertices of
    ICT's published range that generic jawOpen moves) within 20 % of the subject's true jawOpen
    displacement (total relative error ||pred - true|| / ||true|| over those vertices), the upper
    teeth and the skull top (region vertices 10 cm above the mouth) still to 1 % of the lower
    teeth's mean displacement (the skull top: as the model alone predicts it, by less than 2 %: the
    dt model's placement shifts the head a little); eyeLookDown_L moves the eyelashes in the true
    direction (ICT's eye-look shapes do not move the eyeballs: checked too); on the validation
    subjects the followers driven by the true region err by < 10 % (metrics.json)."""
    from fwk.apply import apply
    from fwk.data.io import read_obj, write_obj
    from fwk.plugins import get_registry

    run, tmp = ict_run
    split = json.loads((run / "split.json").read_text())
    full = get_registry().get("dataset", "ict-facekit")(path=str(ICT), region="full", n_subjects=10,
                                                         shapes=["neutral", "jawOpen", "eyeLookDown_L"]).load()
    s = full.subjects.index(split["test"][0])
    P = np.asarray(full.positions[s])
    src = tmp / "head.obj"
    write_obj(src, P[0], full.template)
    apply(run, src, tmp / "out", log=lambda *_: None, say=None)
    got = {e: read_obj(tmp / "out" / f"{e}.obj")[0] for e in ("jawOpen", "eyeLookDown_L")}
    generic = read_obj(ICT / "jawOpen.obj")[0] - read_obj(ICT / "generic_neutral_mesh.obj")[0]
    teeth = np.arange(*TEETH)
    moving = np.linalg.norm(generic[teeth], axis=1) > 0.1
    lower, upper = teeth[moving], teeth[~moving]
    true, pred = P[1] - P[0], got["jawOpen"] - P[0]
    rel = np.linalg.norm(pred[lower] - true[lower]) / np.linalg.norm(true[lower])
    mean_true = np.linalg.norm(true[lower], axis=1).mean()
    mouth_y = P[0, lower, 1].max()
    top = np.flatnonzero(P[0, :N_REGION, 1] > mouth_y + 14.0)  # ICT's jawOpen: < 0.001 cm there
    up_move = np.linalg.norm(pred[upper], axis=1).max()
    top_move = np.linalg.norm(pred[top], axis=1).max()
    top_true = np.linalg.norm(true[top], axis=1).max()
    shift = np.linalg.norm(pred[top].mean(0))
    assert len(lower) > 1000 and len(upper) > 1000 and len(top) > 100, (len(lower), len(upper), len(top))
    assert rel < 0.2, f"lower teeth: relative error {rel:.3f} (true mean displacement {mean_true:.3f} cm)"
    assert up_move < 0.01 * mean_true, f"upper teeth move {up_move:.4f} cm, lower teeth {mean_true:.3f} cm"
    # the skull top is the model's region: the followers leave it as the model predicts it alone
    # (dt places its result by a centroid rule, which shifts the whole head by a few hundredths of
    # a cm: the skull top's motion is that shift, < 2 % of the lower teeth's; truth: < 0.001 cm)
    head = tmp / "region.obj"
    write_obj(head, P[0, :N_REGION], read_obj(run / "template.obj")[1])
    apply(run, head, tmp / "region", expressions=["jawOpen"], log=lambda *_: None, say=None)
    alone = read_obj(tmp / "region" / "jawOpen.obj")[0]
    assert np.allclose(got["jawOpen"][:N_REGION], alone, atol=1e-5), np.abs(got["jawOpen"][:N_REGION] - alone).max()
    assert top_true < 1e-3 and top_move < 0.02 * mean_true, \
        f"skull top moves {top_move:.4f} cm (the model's shift {shift:.4f} cm; truth {top_true:.2e} cm), lower " \
        f"teeth {mean_true:.3f} cm"
    eye = got["eyeLookDown_L"] - P[0]
    lashes = np.arange(*EYELASHES)
    true_eye = P[2] - P[0]
    lash_rel = np.linalg.norm(eye[lashes] - true_eye[lashes]) / np.linalg.norm(true_eye[lashes])
    lash_move = np.linalg.norm(eye[lashes], axis=1).max()
    ball = np.linalg.norm(true_eye[np.arange(*EYEBALL_L)], axis=1).max()
    cos = float((eye[lashes] * true_eye[lashes]).sum() / np.linalg.norm(eye[lashes]) / np.linalg.norm(true_eye[lashes]))
    # the lashes' amplitude is dt's (one source subject's): their direction is checked here, the
    # followers' own accuracy below with the true region driving them
    assert lash_move > 0.1 and cos > 0.95, f"eyelashes: largest move {lash_move:.3f} cm, cosine to the truth {cos:.3f}"
    assert ball == 0.0, f"ICT's eyeLookDown_L moves the left eyeball by {ball:.4f} cm"
    metrics = json.loads((run / "metrics.json").read_text())["followers"]
    for e in ("jawOpen", "eyeLookDown_L"):
        err = metrics["expressions"][e]["all"]
        assert err["truth"] < 0.1, f"{e}: validation error of the followers driven by the true region {err}"
    print(f"lower teeth rel {rel:.4f} (mean true {mean_true:.3f} cm); upper teeth max {up_move:.2e} cm; "
          f"skull top max {top_move:.2e} cm (shift {shift:.2e}, true max {top_true:.2e}); eyelashes rel {lash_rel:.4f}, "
          f"cosine {cos:.4f}, max {lash_move:.3f} cm; "
          f"validation {({e: r['all'] for e, r in metrics['expressions'].items()})}")


# ---------------------------------------------------------------------- the task's follow: (synthetic)
def _heads(root, rng_seed, full: bool, shift: float = 0.0):
    """8 grid heads (tests/rig/conftest.py) in ``root``; ``full``: each with a strip of W + 1
    vertices below the grid appended, moved by the same smooth expressions as the grid."""
    from .conftest import EXPRESSIONS, W, expression, grid_obj, neutral

    rng = np.random.default_rng(rng_seed)
    for s in range(8):
        V = neutral(rng)
        n = len(V)
        extra = V[:W + 1] + np.array([0.0, -1.0, 3.0])
        faces = [[i, i + 1, n + i + 1, n + i] for i in range(W)]
        (root / f"s{s}").mkdir(parents=True)
        for e in ("neutral", *EXPRESSIONS):
            X = np.concatenate([V, extra]) if full else V
            X = X if e == "neutral" else expression(X, e)
            X = X + shift
            (root / f"s{s}" / f"{e}.obj").write_text(
                grid_obj(X[:n], X[n:], faces) if full else grid_obj(X))
    return root


def _recipe(region_root, follow):
    return {"name": "follow-test", "task": "blendshapes", "seed": 0,
            "dataset": {"name": "mesh-folder", "root": str(region_root), "units": "cm"},
            "split": {"ratios": [0.6, 0.2, 0.2]}, "follow": follow,
            "models": {"dt": {"name": "dt", "sources": 0}}, "renders": 0, "metrics": ["l1"]}


def test_task_follow_on_a_synthetic_full_mesh(tmp_path):
    """``follow: {root: FULL}`` on mesh-folder grid heads: stats/followers.npz, the metrics'
    followers section, and fwk apply moving the strip outside the region."""
    from fwk.apply import apply
    from fwk.data.io import read_obj

    from .conftest import W, _execute, expression

    region, full = _heads(tmp_path / "region", 0, False), _heads(tmp_path / "full", 0, True)
    run = _execute(_recipe(region, {"root": str(full)}), tmp_path)
    f = Followers.from_state(load_npz(run / "stats" / "followers.npz"))
    assert f.n == (W + 1) ** 2 and f.n_full == f.n + W + 1 and f.summary()["jawOpen"] == 1
    m = json.loads((run / "metrics.json").read_text())["followers"]
    assert m["split"] == "val" and m["model"] == "dt"
    assert m["expressions"]["jawOpen"]["all"]["truth"] < 0.1, m["expressions"]["jawOpen"]
    assert "follow: 8 vertices outside the region in 1 parts" in (run / "log.txt").read_text()
    test = json.loads((run / "split.json").read_text())["test"][0]
    V, _ = read_obj(full / test / "neutral.obj")
    true = read_obj(full / test / "jawOpen.obj")[0]
    lines = []
    apply(run, full / test / "neutral.obj", tmp_path / "out", log=lambda *_: None, say=lines.append)
    got = read_obj(tmp_path / "out" / "jawOpen.obj")[0]
    n = f.n
    assert any("outside the model's" in x and "move with the face" in x for x in lines), lines
    rel = np.linalg.norm(got[n:] - true[n:]) / np.linalg.norm(true[n:] - V[n:])
    assert np.abs(got[n:] - V[n:]).max() > 0.1 and rel < 0.3, rel
    assert np.allclose(expression(V, "jawOpen")[n:], true[n:])  # the data's own motion, for the record


def test_task_follow_refuses_mismatched_data(tmp_path):
    from fwk.errors import RecipeError

    from .conftest import _execute

    region = _heads(tmp_path / "region", 0, False)
    other = _heads(tmp_path / "other", 1, True)  # other heads: the first vertices differ
    for d in "abcd":
        (tmp_path / d).mkdir()
    with pytest.raises(DataError, match=r"^follow: .* differs from the training data in its first 64 vertices"):
        _execute(_recipe(region, {"root": str(other)}), tmp_path / "a")
    with pytest.raises(DataError, match=r"^follow: .*is not a larger mesh"):
        _execute(_recipe(region, {}), tmp_path / "b")
    with pytest.raises(RecipeError, match="follow.name"):
        _execute(_recipe(region, {"name": "mesh-folder"}), tmp_path / "c")
    with pytest.raises(RecipeError, match="follow"):
        _execute(_recipe(region, 3), tmp_path / "d")
