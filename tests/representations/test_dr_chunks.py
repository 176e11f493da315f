"""dr encodes and decodes many samples in chunks (``CHUNK_BYTES``): the same values as one sample
at a time, with per-sample references and targets kept with their samples, in bounded memory.
All at once, the 1,368 training pairs of the ICT-FaceKit rig (11,248 vertices) took over 22 GB."""
import tracemalloc

import numpy as np
import pytest

import fwk_dr
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
        tracemalloc.start()
        r.raw_features(P)
        out = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return out

    small, whole = peak(2), peak(24)
    out_bytes = 24 * len(V) * 9 * 8 * 2  # the result and its concatenation
    assert small - out_bytes < 0.25 * (whole - out_bytes), (small, whole)
