"""MetricContract: what every metric plugin must satisfy.

Subclass it in a test module and set ``component`` (the metric class) and optionally
``params`` (constructor arguments)::

    class TestMyMetric(MetricContract):
        component = MyMetric

Checked: the metric plays ``fwk.protocols.Metric``: ``name`` and the display attributes
reports read (``label`` a non-empty str, ``display_scale`` > 0, ``units`` a str, ``power`` an
int, ``default`` a bool, ``default_rank`` an int); scores (b,) and per-vertex maps (b, n),
float64 and finite; identical meshes score 0 everywhere; a batch equals its meshes one at a
time; a metric declaring ``rigid_invariant = True`` gives the same scores after a rigid motion
of both meshes; one declaring ``scale_invariant = True`` the same after a uniform scaling,
otherwise scores scale as s**power; a perturbation's score grows with its size on average.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fwk.data import Template
from fwk.protocols import Metric
from fwk.testing import build


def small_mesh():
    """A bumpy open grid (triangles), 9 x 9 vertices, and its Template."""
    n = 9
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    V = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return V, Template(V, F)


class MetricContract:
    """The metric contract suite; set ``component`` (the class) and optionally ``params``."""

    component: type = None
    params: dict = {}

    def make(self):
        return build(self.component, self.params)

    def test_declares_name_and_units(self):
        m = self.make()
        assert isinstance(m, Metric), "a metric declares every attribute of fwk.protocols.Metric"
        assert isinstance(m.name, str) and m.name
        assert isinstance(m.units, str)
        assert (m.__doc__ or "").strip(), "the class docstring is the `fwk list` summary"

    def test_declares_how_reports_show_it(self):
        m = self.make()
        assert isinstance(m.label, str) and m.label.strip(), "label: the column header, e.g. 'L1 norm'"
        assert isinstance(m.display_scale, (int, float)) and not isinstance(m.display_scale, bool)
        assert m.display_scale > 0, "display_scale: tables show value / display_scale"
        assert isinstance(m.power, int) and not isinstance(m.power, bool) and m.power >= 0
        assert isinstance(m.default, bool)
        assert isinstance(m.default_rank, int) and not isinstance(m.default_rank, bool)

    def test_shapes_and_identity(self):
        V, t = small_mesh()
        rng = np.random.default_rng(0)
        P = np.stack([V + rng.normal(0, 0.01, V.shape) for _ in range(3)])
        T = np.stack([V] * 3)
        s, m = self.make()(P, T, t)
        assert s.shape == (3,) and m.shape == (3, len(V))
        assert s.dtype == np.float64 and m.dtype == np.float64
        assert np.all(np.isfinite(s)) and np.all(np.isfinite(m))
        assert np.all(s > 0), "a perturbed mesh must not score 0"
        s0, m0 = self.make()(T, T, t)
        assert s0.shape == (3,) and m0.shape == (3, len(V))
        assert np.allclose(s0, 0, atol=1e-12) and np.allclose(m0, 0, atol=1e-12)

    def test_larger_perturbation_scores_higher(self):
        V, t = small_mesh()
        rng = np.random.default_rng(4)
        noise = rng.normal(0, 1, (6,) + V.shape)
        m = self.make()
        lo = m(V + 0.002 * noise, np.stack([V] * 6), t)[0].mean()
        hi = m(V + 0.02 * noise, np.stack([V] * 6), t)[0].mean()
        assert hi > lo

    def test_batch_equals_single(self):
        V, t = small_mesh()
        rng = np.random.default_rng(1)
        P = np.stack([V + rng.normal(0, 0.01, V.shape) for _ in range(2)])
        T = np.stack([V, V + 0.001])
        s, m = self.make()(P, T, t)
        for i in range(2):
            si, mi = self.make()(P[i:i + 1], T[i:i + 1], t)
            assert np.allclose(si, s[i]) and np.allclose(mi, m[i])

    def test_rigid_invariance_when_declared(self):
        m = self.make()
        # rigid_invariant / scale_invariant are optional declarations (absent: not claimed)
        if not getattr(m, "rigid_invariant", False):
            return
        V, t = small_mesh()
        rng = np.random.default_rng(2)
        P = V + rng.normal(0, 0.01, V.shape)
        R = Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix()
        s1, m1 = m(P[None], V[None], t)
        s2, m2 = m((P @ R.T + 3.0)[None], (V @ R.T + 3.0)[None], t)
        assert np.allclose(s1, s2, rtol=1e-8, atol=1e-12) and np.allclose(m1, m2, rtol=1e-7, atol=1e-10)

    def test_uniform_scale(self):
        """scale_invariant: same scores after scaling both meshes; otherwise, with a declared
        ``power`` p, the scores scale as s**p."""
        m = self.make()
        V, t = small_mesh()
        P = V + np.random.default_rng(5).normal(0, 0.01, V.shape)
        s1, _ = m(P[None], V[None], t)
        s2, _ = m((2.5 * P)[None], (2.5 * V)[None], t)
        if getattr(m, "scale_invariant", False):
            assert np.allclose(s1, s2, rtol=1e-8, atol=1e-12)
        else:
            assert np.allclose(s2, s1 * 2.5 ** m.power, rtol=1e-10)
