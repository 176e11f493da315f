import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fwk.data.preprocess import PreprocessConfig, Preprocessor
from fwk.data.split import SplitConfig, split_subjects
from fwk.geometry import kabsch


def _subjects(seed=0, S=8, n=40):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(n, 3)) * [7, 11, 9]
    N = np.stack([(base + rng.normal(0, 0.2, base.shape)) @ Rotation.random(random_state=i).as_matrix().T
                  + rng.normal(0, 5, 3) for i in range(S)])
    E = N + rng.normal(0, 0.3, N.shape)
    return N, np.stack([N, E], axis=1)


def test_kabsch_recovers_rotation_and_fixes_reflection():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(30, 3))
    R0 = Rotation.random(random_state=3).as_matrix()
    R, t = kabsch(A, A @ R0.T + [1, 2, 3])
    assert np.allclose(R, R0, atol=1e-12) and np.allclose(t, [1, 2, 3], atol=1e-12)
    R, _ = kabsch(A, A * [-1, 1, 1])  # a mirror: the best proper rotation, never a reflection
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_preprocess_registers_scales_and_inverts():
    N, P = _subjects()
    pre = Preprocessor().fit(N, P)
    X, T = pre.transform(P, N)
    assert np.abs(X).max() == pytest.approx(1.0)
    assert np.allclose(pre.inverse(X, T), P, atol=1e-10)
    # registered neutrals are rigidly aligned to the mean: re-registering changes nothing
    R, t = kabsch(X[0, 0], pre.mean_neutral)
    assert np.allclose(R, np.eye(3), atol=1e-6)
    # expressions follow their neutral's transform
    assert np.allclose(X[:, 1] - X[:, 0], T.scale * np.einsum("sij,snj->sni", T.rotation, P[:, 1] - P[:, 0]))
    # a new head registered with the saved state equals the training transform
    pre2 = Preprocessor.from_state(pre.state_dict())
    X2, _ = pre2.transform_neutrals(N[3])
    assert np.allclose(X2, X[3, 0], atol=1e-10)


def test_preprocess_recovers_known_rigid_motion():
    N, _ = _subjects(S=1)
    R0 = Rotation.from_euler("xyz", [0.2, 0.7, -0.4]).as_matrix()
    moved = N[0] @ R0.T + [10, -3, 4]
    pre = Preprocessor(PreprocessConfig(scale=False)).fit(N)
    X, T = pre.transform_neutrals(moved[None])
    assert np.allclose(X[0], pre.mean_neutral, atol=1e-9)


def test_split_seeded_by_subject():
    subjects = [f"s{i}" for i in range(40)]
    a = split_subjects(subjects, SplitConfig(), seed=3)
    b = split_subjects(subjects, SplitConfig(), seed=3)
    c = split_subjects(subjects, SplitConfig(), seed=4)
    assert a == b and a != c
    assert sorted(a["train"] + a["val"] + a["test"]) == sorted(subjects)
    assert (len(a["train"]), len(a["val"]), len(a["test"])) == (34, 2, 4)
    small = split_subjects(["a", "b", "c"], SplitConfig(), seed=0)
    assert all(len(v) == 1 for v in small.values())


def test_kabsch_matches_a_naive_reference():
    """Against a brute-force search over proper rotations near the answer and scipy's solver,
    on a configuration where the plain SVD solution is a reflection."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(12, 3))
    B = A * [1, 1, -1] + rng.normal(0, 0.05, A.shape)  # mirrored: det(V U^T) = -1 without the fix
    R, t = kabsch(A, B)
    cost = lambda Q: ((A - A.mean(0)) @ Q.T - (B - B.mean(0))) ** 2
    ref, _ = Rotation.align_vectors(B - B.mean(0), A - A.mean(0))
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert cost(R).sum() == pytest.approx(cost(ref.as_matrix()).sum(), rel=1e-9)
    for Q in Rotation.random(2000, random_state=0).as_matrix():
        assert cost(R).sum() <= cost(Q).sum() + 1e-12
    # batched equals one by one
    Rb, tb = kabsch(np.stack([A, B]), np.stack([B, A]))
    assert np.allclose(Rb[0], R) and np.allclose(Rb[1], kabsch(B, A)[0])


def test_split_and_preprocess_moves_each_subject_rigidly_and_inverts(tmp_path):
    import json

    import numpy as np

    from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
    from fwk.data.split import SplitConfig
    from fwk.plugins import get_registry
    from fwk.runs import make_test_context

    ctx = make_test_context(tmp_path)
    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=12, n_vertices=300,
                                                          shapes=["neutral", "face-compression"]).load(None)
    P0 = np.asarray(col.positions).copy()
    split, pre, cols, T = split_and_preprocess(col, SplitConfig(ratios=[0.5, 0.25, 0.25]), PreprocessConfig(), 0, ctx)
    assert json.loads((ctx.run_dir / "split.json").read_text()) == split
    assert (ctx.run_dir / "stats" / "preprocess.npz").exists()
    assert sorted(sum(split.values(), [])) == sorted(col.subjects)
    index = {s: i for i, s in enumerate(col.subjects)}
    for name in ("train", "val", "test"):
        X = np.asarray(cols[name].positions)
        orig = P0[[index[s] for s in split[name]]]
        # every shape of a subject moved with its neutral: expression - neutral offsets keep their length
        d0 = np.linalg.norm(orig[:, 1] - orig[:, 0], axis=-1)
        d1 = np.linalg.norm(X[:, 1] - X[:, 0], axis=-1) / pre.scale
        np.testing.assert_allclose(d1, d0, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(pre.inverse(X, T[name]), orig, atol=1e-9)
