import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fwk.data import MeshCollection
from fwk.protocols import FitData
from fwk_dt import DeformationTransfer


def _collection(n_subjects=3):
    from fwk.plugins import get_registry

    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=400,
                                                            shapes=["neutral", "mouth-wide"]).load(None)
    P = np.asarray(col.positions).copy()
    P -= P[:, :1].mean(axis=2, keepdims=True)  # centre every subject on its neutral's centroid
    col.positions = P
    return col


def _fit(col, sources=0):
    m = DeformationTransfer(sources=sources)
    m.fit(FitData(col.template, col, col, ["neutral"]))
    return m


def test_same_source_and_target_reproduces_the_expression():
    col = _collection()
    m = _fit(col, 1)
    P = np.asarray(col.positions)
    out = m.predict(P[1:2, 0], "mouth-wide")
    assert np.abs(out[0] - P[1, 1]).max() < 1e-9


@pytest.mark.parametrize("kind", ["rigid", "similarity", "affine"])
def test_global_source_deformation_transfers_exactly(kind):
    col = _collection()
    P = np.asarray(col.positions).copy()
    A = Rotation.from_euler("xyz", [0.2, -0.4, 0.3]).as_matrix()
    if kind == "similarity":
        A = 1.3 * A
    if kind == "affine":
        A = A @ np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]])
    P[0, 1] = P[0, 0] @ A.T  # the source "expression" is a global map of its neutral
    col.positions = P
    m = _fit(col, 0)
    out = m.predict(P[1:3, 0], "mouth-wide")
    targets = P[1:3, 0] if kind != "affine" else P[0:1, 0]
    out = m.predict(targets, "mouth-wide")
    for i, T0 in enumerate(targets):
        expect = T0 @ A.T
        expect = expect - expect.mean(0) + T0.mean(0) + (P[0, 1] - P[0, 0]).mean(0)
        assert np.abs(out[i] - expect).max() < 1e-9


def test_general_affine_to_another_head_is_close():
    """Sumner's fourth vertex n / sqrt|n| is not affine-covariant: a shear is transferred exactly
    only on the triangle planes source and target share. On another head the error is small."""
    col = _collection()
    P = np.asarray(col.positions).copy()
    A = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]])
    P[0, 1] = P[0, 0] @ A.T
    col.positions = P
    out = _fit(col, 0).predict(P[1:2, 0], "mouth-wide")[0]
    expect = P[1, 0] @ A.T
    expect = expect - expect.mean(0) + P[1, 0].mean(0)
    size = np.abs(P[1, 0]).max()
    assert np.abs(out - expect).max() < 0.02 * size


def test_transfer_is_personalised_and_several_sources_average():
    col = _collection(4)
    P = np.asarray(col.positions)
    one = _fit(col, 0).predict(P[2:4, 0], "mouth-wide")
    two = _fit(col, [0, 1]).predict(P[2:4, 0], "mouth-wide")
    assert np.all(np.isfinite(one)) and not np.allclose(one, two)
    d = one - P[2:4, 0]
    assert not np.allclose(d[0], d[1])  # different neutrals get different displacements
    m = _fit(col, 0)
    allx = m.predict_all(P[2:4, 0], ["mouth-wide"])
    assert np.allclose(allx["mouth-wide"], one)
    m2 = DeformationTransfer()
    m2.load_state_dict(m.state_dict())
    assert np.allclose(m2.predict(P[2:3, 0], "mouth-wide"), one[:1])


def test_predict_all_one_neutral_at_a_time_equals_each_neutral_alone():
    """predict_all factorises one neutral at a time (memory of one system): the same numbers as
    a loop over the neutrals, each predicted alone, for every expression."""
    from fwk.plugins import get_registry

    col = get_registry().get("dataset", "synthetic-heads")(
        n_subjects=4, n_vertices=400, shapes=["neutral", "mouth-wide", "face-compression"]).load(None)
    m = _fit(col, sources=[0, 1])
    N = np.asarray(col.positions[:, 0])
    got = m.predict_all(N, ["mouth-wide", "face-compression"])
    for e in ("mouth-wide", "face-compression"):
        want = np.stack([m.predict(N[i:i + 1], e)[0] for i in range(len(N))])
        assert np.array_equal(got[e], want)
    with pytest.raises(Exception, match="no source"):
        m.predict_all(N, ["nope"])


def test_sources_mean_is_dt_from_the_mean_subject():
    """``sources: mean``: the same as DT from a subject whose neutral and expression are the
    training subjects' means (built here by hand, a loop over subjects), and the state holds those
    means only (no subject's own mesh)."""
    col = _collection(n_subjects=4)
    P = np.asarray(col.positions)
    m = _fit(col, "mean")
    N, E = np.zeros_like(P[0, 0]), np.zeros_like(P[0, 1])
    for s in range(len(P)):  # the naive means
        N += P[s, 0] / len(P)
        E += P[s, 1] / len(P)
    ref_col = MeshCollection(col.template, ["mean", *col.subjects], col.shape_names,
                             np.concatenate([np.stack([N, E])[None], P]))
    ref = _fit(ref_col, 0)
    out, want = m.predict(P[:, 0], "mouth-wide"), ref.predict(P[:, 0], "mouth-wide")
    assert np.abs(out - want).max() < 1e-12
    st = m.state_dict()
    S0, S1 = st["neutral"], st["expressions"]["mouth-wide"]
    assert S0.shape == (1, *N.shape) and np.allclose(S0[0], N) and np.allclose(S1[0], E)
    assert "src" not in st  # the mean neutral once, not once per expression
    for s in range(len(P)):  # no subject's own neutral is kept
        assert not np.allclose(S0[0], P[s, 0])
    assert "mean training subject" in m.describe()


def test_sources_mean_survives_the_safe_format(tmp_path):
    from fwk.safeio import load_state, save_state

    col = _collection()
    m = _fit(col, "mean")
    save_state(tmp_path / "dt.safetensors", m.state_dict())
    back = DeformationTransfer()
    back.load_state_dict(load_state(tmp_path / "dt.safetensors"))
    assert back.sources == "mean" and back.expressions == ["mouth-wide"]
    P = np.asarray(col.positions)
    assert np.array_equal(back.predict(P[:2, 0], "mouth-wide"), m.predict(P[:2, 0], "mouth-wide"))
    old = DeformationTransfer()  # the form sources: mean was saved in before: every expression's (N, E)
    old.load_state_dict({"sources": "mean", "F": m.F, "src": dict(m.src)})
    assert np.array_equal(old.predict(P[:2, 0], "mouth-wide"), m.predict(P[:2, 0], "mouth-wide"))


def test_sources_mean_is_a_recipe_value_and_other_words_are_refused():
    from fwk.errors import RecipeError
    from fwk.testing import build

    assert build(DeformationTransfer, {"sources": "mean"}).sources == "mean"
    assert build(DeformationTransfer, {"sources": [0, 2]}).sources == [0, 2]
    with pytest.raises(RecipeError):
        build(DeformationTransfer, {"sources": "median"})


def test_sources_mean_packed_state_is_lossless():
    """The packed state (fwk pack): a bit mask of the moved vertices and their offsets; every mean
    expression comes back to round-off, the unmoved vertices exactly, and so does the transfer."""
    col = _collection(n_subjects=4)
    m = _fit(col, "mean")
    st = m.packed_state()
    assert st["sources"] == "mean" and "src" not in st
    back = DeformationTransfer()
    back.load_state_dict(st)
    N = m.src["mouth-wide"][0]
    for e, (_, E) in m.src.items():
        got = back.src[e][1]
        assert np.abs(got - E).max() <= 1e-12 * max(np.abs(E).max(), 1.0), e
        still = np.all(E[0] == N[0], axis=1)
        assert np.array_equal(got[0, still], N[0, still]), e
        assert len(st["moved"][e]["offsets"]) == int((~still).sum())
    P = np.asarray(col.positions)
    want, have = m.predict(P[:2, 0], "mouth-wide"), back.predict(P[:2, 0], "mouth-wide")
    assert np.abs(have - want).max() <= 1e-10
    bad = dict(st, moved={"mouth-wide": dict(st["moved"]["mouth-wide"], offsets=np.zeros((1, 3)))})
    with pytest.raises(Exception, match="moved vertices"):
        DeformationTransfer().load_state_dict(bad)


def test_median_placement_is_the_per_coordinate_median_and_keeps_still_vertices_still():
    """placement: median: the solved result translated by the median over vertices of
    (T0 + d - X), computed here by a loop over coordinates; on the source itself the result is the
    same as the centroid rule's (the source's expression back); on another target, vertices the
    source leaves still move less than with the centroid rule (the jaw-opening case)."""
    from fwk_dt import TargetSystem

    col = _collection(n_subjects=4)
    P = np.asarray(col.positions)
    m, c = _fit(col, 0), _fit(col, 0)
    m.placement = "median"
    T0 = P[1, 0]
    Q, disp, _ = m._source_maps("mouth-wide")
    X = TargetSystem(T0, m.F).solve(Q, T0[TargetSystem(T0, m.F).pins] + disp[TargetSystem(T0, m.F).pins])
    t = np.array([sorted((T0 + disp - X)[:, k])[len(X) // 2] if len(X) % 2 else
                  0.5 * (sorted((T0 + disp - X)[:, k])[len(X) // 2 - 1] + sorted((T0 + disp - X)[:, k])[len(X) // 2])
                  for k in range(3)])
    assert np.allclose(m.predict(T0[None], "mouth-wide")[0], X + t, atol=1e-12)
    assert np.allclose(m.predict(P[:1, 0], "mouth-wide"), P[:1, 1], atol=1e-8)  # the source itself
    assert "median" in m.describe()
    # a local expression: the source moves only its upper third (a bump); on another subject's
    # neutral the vertices it leaves still stay (near) still with the median, not with the centroid
    Pl = P.copy()
    y = Pl[:, 0, :, 1]
    top = y > np.quantile(y, 2 / 3, axis=1, keepdims=True)
    Pl[:, 1] = Pl[:, 0]
    Pl[:, 1, :, 2] += 0.3 * top * (y - np.quantile(y, 2 / 3, axis=1, keepdims=True))
    local = MeshCollection(col.template, col.subjects, col.shape_names, Pl)
    med, cen = _fit(local, 0), _fit(local, 0)
    med.placement = "median"
    still = ~top[1]
    a = np.abs(med.predict(Pl[1:2, 0], "mouth-wide")[0, still] - Pl[1, 0, still])
    b = np.abs(cen.predict(Pl[1:2, 0], "mouth-wide")[0, still] - Pl[1, 0, still])
    assert np.median(a) < 0.2 * np.median(b), (np.median(a), np.median(b))
