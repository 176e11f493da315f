"""AssemblerContract: what every assembler plugin must satisfy (``fwk.protocols.Assembler``).

Subclass it and set ``component`` and ``params``; ``ks`` are the cut points ``assemble_many`` is
checked at (each within the fitted basis). Checked on an assembler fitted (``fit(template, mean,
cache=...)``) on an ellipsoid of 162 vertices: the class defines every member of the role;
``split`` gives at least two bands of the input's shape, each centred on the mean (the mean mesh
splits into copies of the mean), linear in P - mean and independent across the batch;
``assemble(split(P)) == P``; ``assemble_many([low, high], ks)`` has shape (len(ks), b, n, 3),
returns the input for two equal sources and the high source at k = 0, and equals its cut points
computed one at a time; ``band_shares(D)`` of displacements is (b, bands), finite, non-negative,
each row summing to 1 (a share of the energy); ``state_dict`` / ``load_state_dict(d, ctx=None)``
restore the same split; an assembler playing ``TruncatesCuts`` restores from
``truncated_state(k)`` one that assembles every cut up to k as before.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fwk.cache import Cache
from fwk.data import Template
from fwk.protocols import Assembler, TruncatesCuts, plays
from fwk.testing import build
from fwk.testing.model import safe_round_trip


class AssemblerContract:
    component: type = None
    params: dict = {}
    ks: list = [0, 1, 5, 10]

    def fitted(self, cache=None):
        m = trimesh.creation.icosphere(subdivisions=2)
        V = np.asarray(m.vertices) * [1.0, 1.3, 0.8]
        t = Template(V, np.asarray(m.faces))
        a = build(self.component, self.params)
        a.fit(t, V, cache=cache)
        rng = np.random.default_rng(0)
        P = np.stack([V + rng.normal(0, 0.02, V.shape) for _ in range(3)])
        return a, P, V

    def test_declares_name_and_plays_the_role(self, tmp_path):
        assert isinstance(self.component.name, str) and self.component.name
        assert plays(self.component, Assembler), "the class must define every member of Assembler"
        a, P, V = self.fitted(Cache(tmp_path / "cache"))
        assert isinstance(a, Assembler)
        assert np.allclose(a.assemble(a.split(P)), P, atol=1e-10)

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

    def test_assemble_many(self):
        a, P, V = self.fitted()
        Q = P[::-1].copy()
        out = a.assemble_many([P, Q], self.ks)
        assert out.shape == (len(self.ks), *P.shape)
        assert np.allclose(a.assemble_many([P, P], self.ks), np.broadcast_to(P, out.shape), atol=1e-10)
        if 0 in self.ks:
            assert np.allclose(out[self.ks.index(0)], Q, atol=1e-10)
        for i, k in enumerate(self.ks):
            assert np.allclose(a.assemble_many([P, Q], [k])[0], out[i], atol=1e-10)

    def test_band_shares_are_shares(self):
        a, P, V = self.fitted()
        bands = a.split(P)
        s = np.asarray(a.band_shares(P - V))
        assert s.shape == (len(P), len(bands)), f"band_shares: (b, bands) = {(len(P), len(bands))}, got {s.shape}"
        assert np.all(np.isfinite(s)) and np.all(s >= -1e-12), f"band_shares must be finite and >= 0: {s}"
        assert np.allclose(s.sum(1), 1.0, atol=1e-6), f"each mesh's shares sum to 1, got {s.sum(1)}"

    def test_state_round_trip(self):
        a, P, V = self.fitted()
        b = build(self.component, self.params)
        b.load_state_dict(a.state_dict(), ctx=None)
        assert np.allclose(b.assemble(b.split(P)), P, atol=1e-10)
        assert all(np.allclose(x, y) for x, y in zip(a.split(P), b.split(P)))
        assert np.allclose(b.assemble_many([P, P[::-1]], self.ks), a.assemble_many([P, P[::-1]], self.ks))

    def test_truncated_state(self):
        """Optional role ``TruncatesCuts``: the state cut at k (every k of ``ks`` up to the largest)
        loads into an assembler that assembles two bands at every cut up to k as this one does."""
        a, P, V = self.fitted()
        if not isinstance(a, TruncatesCuts):
            pytest.skip(f"{self.component.name} does not play TruncatesCuts")
        Q = P[::-1].copy()
        for k in [k for k in self.ks if k > 0]:
            b = build(self.component, {**self.params, "k": k})
            b.load_state_dict(safe_round_trip(a.truncated_state(k)), ctx=None)
            cuts = [c for c in self.ks if c <= k]
            assert np.allclose(b.assemble_many([P, Q], cuts), a.assemble_many([P, Q], cuts), atol=1e-12), k
