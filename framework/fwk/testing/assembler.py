"""AssemblerContract: bands split and assemble back exactly; shapes; state round trip."""
from __future__ import annotations

import numpy as np


class AssemblerContract:
    component: type = None
    params: dict = {}

    def fitted(self):
        import trimesh

        from fwk.data import Template

        m = trimesh.creation.icosphere(subdivisions=2)
        V = np.asarray(m.vertices) * [1.0, 1.3, 0.8]
        t = Template(V, np.asarray(m.faces))
        a = self.component(**self.params)
        a.fit(t, V)
        rng = np.random.default_rng(0)
        P = np.stack([V + rng.normal(0, 0.02, V.shape) for _ in range(3)])
        return a, P

    def test_split_assemble_exact(self):
        a, P = self.fitted()
        bands = a.split(P)
        assert len(bands) >= 2 and all(b.shape == P.shape for b in bands)
        assert np.allclose(a.assemble(bands), P, atol=1e-10)

    def test_state_round_trip(self):
        a, P = self.fitted()
        b = self.component(**self.params)
        b.load_state_dict(a.state_dict())
        assert np.allclose(b.assemble(b.split(P)), P, atol=1e-10)
        assert all(np.allclose(x, y) for x, y in zip(a.split(P), b.split(P)))
