"""dr encodes and decodes many samples in chunks (``CHUNK_BYTES``): the same values as one sample
at a time, with per-sample references and targets kept with their samples, in bounded memory.
All at once, the 1,368 training pairs of the ICT-FaceKit rig (11,248 vertices) took over 22 GB."""
import tracemalloc

import numpy as np
import pytest

import fwk_dr
from fwk.cache import forget
from fwk.plugins import get_registry
from tests.representations.test_dr_reference import head, smooth_deformation  # noqa: F401 (fixture)

DR = get_registry().get("representation", "dr")


def _samples(V, n, seed0=0, amplitude=0.05):
    return np.stack([smooth_deformation(V, seed0 + s, amplitude) for s in range(n)])


@pytest.mark.parametrize("ref", ["mean", "sample"])
def test_chunks_give_the_values_of_one_sample_at_a_time(head, monkeypatch, ref):  # noqa: F811
    V, t = head
    P = _samples(V, 7)
    R = _samples(V, 7, seed0=100, amplitude=0.02) if ref == "sample" else None
    r = DR(scaling="std", ref=ref)
    r.fit(P, R, t)
    one = [r.encode(P[i], None if R is None else R[i]) for i in range(len(P))]
    dec1 = [r.decode(one[i], None if R is None else R[i], P[i]) for i in range(len(P))]
    per_sample = len(r._ops["hi"]) * 10 * 8
    monkeypatch.setattr(fwk_dr, "CHUNK_BYTES", 3 * per_sample)  # chunks of 3, 3 and 1
    assert r._chunk() == 3
    F = r.encode(P, R)
    assert F.shape == (7, len(V), 9)
    np.testing.assert_array_equal(F, np.stack(one))
    X = r.decode(F, R, P)
    np.testing.assert_allclose(X, np.stack(dec1), rtol=0, atol=1e-12)
    X2 = r.decode(F, R)  # placed on the references, no target
    np.testing.assert_allclose(X2[4], r.decode(F[4], None if R is None else R[4]), rtol=0, atol=1e-12)


def test_memory_is_bounded_by_the_chunk(head, monkeypatch):  # noqa: F811
    """Peak memory of encoding 24 samples grows with the chunk, not with the number of samples."""
    V, t = head
    P = _samples(V, 24)
    r = DR(scaling="none")
    r.fit(P[:2], None, t)
    per_sample = len(r._ops["hi"]) * 10 * 8

    def peak(chunk):
        monkeypatch.setattr(fwk_dr, "CHUNK_BYTES", chunk * per_sample)
        forget("fwk_dr.raw_features")  # computed afresh, not remembered from the call before
        tracemalloc.start()
        r.raw_features(P)
        out = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return out

    small, whole = peak(2), peak(24)
    out_bytes = 24 * len(V) * 9 * 8 * 2  # the result and its concatenation
    assert small - out_bytes < 0.25 * (whole - out_bytes), (small, whole)


def _count_batches(monkeypatch):
    """Forgets the remembered features and records the size of every batch ``DR._raw_features``
    computes from then on; returns (those sizes, the real ``_raw_features``)."""
    forget("fwk_dr.raw_features")
    sizes = []
    real = fwk_dr.DR._raw_features
    monkeypatch.setattr(fwk_dr.DR, "_raw_features", lambda self, P, r: sizes.append(len(P)) or real(self, P, r))
    return sizes, real


def test_features_are_remembered_for_the_same_meshes_only(head, monkeypatch):  # noqa: F811
    """fit then encode of the same meshes computes the features once; other meshes, another
    reference, another fitted mean or another parameter compute afresh; a remembered result
    equals a fresh one, and writing into it leaves the remembered one alone; results over
    MEMO_BYTES are not remembered."""
    # (the same meshes in other batches: test_features_are_remembered_mesh_by_mesh)
    V, t = head
    P = _samples(V, 4)
    R = _samples(V, 4, seed0=100, amplitude=0.02)
    calls, real = _count_batches(monkeypatch)
    r = DR(scaling="std")
    r.fit(P, None, t)
    X = r.encode(P)
    assert len(calls) == 1
    F = r.raw_features(P)
    assert len(calls) == 1 and np.array_equal(F, real(r, P, None))
    F[0, 0, 0] += 1.0
    assert np.array_equal(r.raw_features(P), real(r, P, None)) and len(calls) == 1
    assert np.array_equal(X, r.scaler.transform(real(r, P, None)).astype(np.float32))
    r.raw_features(P[:3] + 0.01)  # other meshes
    r.raw_features(P, R)  # another reference
    DR(scaling="std", normal_weight=0.2).fit(P, None, t)  # another parameter
    r2 = DR(scaling="std")
    r2.fit(P[:3], None, t)  # another fitted mean
    r2.raw_features(P)
    assert len(calls) == 6
    forget("fwk_dr.raw_features")
    monkeypatch.setattr(fwk_dr, "MEMO_BYTES", P.size * 3 * 8 - 1)  # too large to remember
    r.raw_features(P)
    r.raw_features(P)
    assert len(calls) == 8


def test_features_are_remembered_mesh_by_mesh(head, monkeypatch):  # noqa: F811
    """Meshes fitted together and encoded in other batches (PB's expression networks: every
    expression at once, then expression by expression), each with its own reference, are computed
    once; only the meshes not seen are computed, in one batch; the results equal fresh ones (to the
    polar decomposition's tolerance: the batch decides its last iteration); the oldest meshes are
    dropped first when MEMO_BYTES would be passed."""
    V, t = head
    P = _samples(V, 6)
    R = _samples(V, 6, seed0=100, amplitude=0.02)
    batches, real = _count_batches(monkeypatch)
    r = DR(scaling="std")
    r.fit(P, R, t)
    assert batches == [6]
    for part in (slice(0, 3), slice(3, 6), [5, 0]):
        F = r.raw_features(P[part], R[part])
        assert np.allclose(F, real(r, P[part], R[part]), rtol=0, atol=1e-12)
    assert batches == [6]  # the three batches were all remembered
    Q = np.concatenate([P[:2], _samples(V, 2, seed0=50)])
    F = r.raw_features(Q, np.concatenate([R[:2], R[:2]]))
    assert batches == [6, 2] and np.allclose(F, real(r, Q, np.concatenate([R[:2], R[:2]])), atol=1e-12)
    one = P[0].size * 3 * 8  # one mesh's (n, 9) float64 features
    forget("fwk_dr.raw_features")
    monkeypatch.setattr(fwk_dr, "MEMO_BYTES", 4 * one)
    batches.clear()
    r.raw_features(P[:4], R[:4])
    r.raw_features(P[4:6], R[4:6])  # drops meshes 0 and 1
    r.raw_features(P[:4], R[:4])
    assert batches == [4, 2, 2]
