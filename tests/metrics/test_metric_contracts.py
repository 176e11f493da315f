import sys
from pathlib import Path

import numpy as np
import pytest

from fwk.plugins import get_registry
from fwk.testing.metric import MetricContract, small_mesh

REG = get_registry()
PLUGINS = Path(__file__).resolve().parents[2] / "plugins"


def _builtin(cls) -> bool:
    """A metric of fwk's own plugins (not a third-party package installed beside it)."""
    return PLUGINS in Path(sys.modules[cls.__module__].__file__).resolve().parents


BUILTIN = sorted(e.name for e in REG if e.kind == "metric" and _builtin(e.component))

# one contract suite per built-in metric (TestContract_l1, ...), so a new one is covered at once
for _name in BUILTIN:
    globals()[f"TestContract_{_name}"] = type(f"TestContract_{_name}", (MetricContract,),
                                              {"component": REG.get("metric", _name)})


def test_builtins_found():
    assert BUILTIN == ["dame", "euclidean", "fmpd", "l1", "l2"]


@pytest.mark.parametrize("name", ["l1", "l2", "euclidean", "dame", "fmpd"])
def test_registered(name):
    assert name in REG.names("metric")


@pytest.mark.parametrize("name", ["l1", "l2", "euclidean", "dame", "fmpd"])
def test_single_mesh_is_a_batch_of_one(name):
    """fwk's own metrics also take one (n, 3) mesh (not required of third-party metrics)."""
    V, t = small_mesh()
    P = V + np.random.default_rng(3).normal(0, 0.01, V.shape)
    m = REG.get("metric", name)()
    s1, m1 = m(P, V, t)
    s2, m2 = m(P[None], V[None], t)
    assert s1.shape == (1,) and m1.shape == (1, len(V))
    assert np.allclose(s1, s2) and np.allclose(m1, m2)


@pytest.mark.parametrize("name,label,scale,units,power", [
    ("l1", "L1 norm", 1e-3, "input", 1), ("l2", "L2 norm", 1e-5, "input^2", 2),
    ("euclidean", "Euclidean", 1e-3, "input", 1), ("dame", "DAME", 1e-2, "rad", 0), ("fmpd", "FMPD", 1e-2, "1", 0)])
def test_display_attributes_are_the_thesis_factors(name, label, scale, units, power):
    cls = REG.get("metric", name)
    assert (cls.label, cls.display_scale, cls.units, cls.power, cls.default) == (label, scale, units, power, True)
