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
