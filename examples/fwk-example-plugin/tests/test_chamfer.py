"""The example plugin reuses fwk's metric contract suite, as any third-party plugin should."""
import numpy as np

from fwk.testing.metric import MetricContract
from fwk_example_plugin import Chamfer


class TestChamferContract(MetricContract):
    component = Chamfer


def test_chamfer_naive():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(1, 20, 3)), rng.normal(size=(1, 20, 3))
    d = np.linalg.norm(a[0][:, None] - b[0][None], axis=-1)
    s, m = Chamfer()(a, b, None)
    assert np.allclose(m[0], d.min(1))
    assert np.isclose(s[0], 0.5 * (d.min(1).mean() + d.min(0).mean()))
