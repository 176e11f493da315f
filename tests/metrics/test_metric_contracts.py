import pytest

from fwk.plugins import get_registry
from fwk.testing.metric import MetricContract

REG = get_registry()


@pytest.mark.parametrize("name", ["l1", "l2", "euclidean", "dame", "fmpd"])
def test_registered(name):
    assert name in REG.names("metric")


class TestL1(MetricContract):
    component = REG.get("metric", "l1")


class TestL2(MetricContract):
    component = REG.get("metric", "l2")


class TestEuclidean(MetricContract):
    component = REG.get("metric", "euclidean")


class TestDAME(MetricContract):
    component = REG.get("metric", "dame")


class TestFMPD(MetricContract):
    component = REG.get("metric", "fmpd")


@pytest.mark.parametrize("name", ["l1", "l2", "euclidean", "dame", "fmpd"])
def test_single_mesh_is_a_batch_of_one(name):
    """fwk's own metrics also take one (n, 3) mesh (not required of third-party metrics)."""
    import numpy as np

    from fwk.testing.metric import small_mesh

    V, t = small_mesh()
    P = V + np.random.default_rng(3).normal(0, 0.01, V.shape)
    m = REG.get("metric", name)()
    s1, m1 = m(P, V, t)
    s2, m2 = m(P[None], V[None], t)
    assert s1.shape == (1,) and m1.shape == (1, len(V))
    assert np.allclose(s1, s2) and np.allclose(m1, m2)
