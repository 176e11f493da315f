"""AssemblerContract: what every assembler plugin must satisfy.

Subclass it and set ``component`` and ``params``. Checked on a fitted assembler (an ellipsoid,
162 vertices): ``split`` gives at least two bands of the input's shape, each centred on the mean
(the mean mesh splits into copies of the mean), linear in P - mean and independent across the
batch; ``assemble(split(P)) == P``; ``state_dict`` restores the same split.
"""
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
        return a, P, V

    def test_declares_name(self):
        assert isinstance(self.component.name, str) and self.component.name

    def test_split_assemble_exact(self):
        a, P, V = self.fitted()
        bands = a.split(P)
        assert len(bands) >= 2 and all(b.shape == P.shape for b in bands)
        assert np.allclose(a.assemble(bands), P, atol=1e-10)

    def test_bands_are_centred_on_the_mean_and_linear(self):
        a, P, V = self.fitted()
        for b in a.split(V[None]):
            assert np.allclose(b[0], V, atol=1e-10)
        B1, B2 = a.split(P[:1]), a.split(P[1:2])
        Bs = a.split(P[:1] + 2.0 * (P[1:2] - V))
        for x, y, z in zip(B1, B2, Bs):
            assert np.allclose(z - V, (x - V) + 2.0 * (y - V), atol=1e-10)
        # displacements of all bands sum to P - mean
        assert np.allclose(sum(b - V for b in a.split(P)), P - V, atol=1e-10)

    def test_batch_is_independent(self):
        a, P, V = self.fitted()
        whole = a.split(P)
        for i in range(len(P)):
            for b, w in zip(a.split(P[i:i + 1]), whole):
                assert np.allclose(b, w[i:i + 1], atol=1e-12)

    def test_state_round_trip(self):
        a, P, V = self.fitted()
        b = self.component(**self.params)
        b.load_state_dict(a.state_dict())
        assert np.allclose(b.assemble(b.split(P)), P, atol=1e-10)
        assert all(np.allclose(x, y) for x, y in zip(a.split(P), b.split(P)))
