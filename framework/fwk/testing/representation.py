"""RepresentationContract: what every representation plugin must satisfy.

Subclass it and set ``component`` (the class) and ``params`` (constructor arguments)::

    class TestMine(RepresentationContract):
        component = Mine
        params = {"scaling": "std"}
        atol = 1e-6          # round-trip tolerance on ``small_batch`` (noisy, not smooth)

Checked: the class defines every member of ``fwk.protocols.Representation`` and a fitted
instance plays it; ``channels``; ``places_rigidly`` and ``relative`` are declared booleans and
``relative_option`` a class attribute (with it, the constructor takes ``relative``); encode gives
(b, n, channels) float32 and decode (b, n, 3) float64 that round-trips (with the ground truth
passed as ``target``, which representations that place rigidly, such as dr, use to place the
result; without a target where ``places_rigidly`` is false); a batch encodes as its meshes one by
one; fitting on two meshes works and gives finite features; ``unscale`` is differentiable and
equals the features of the same representation with ``scaling: none``; ``state_dict`` /
``load_state_dict(d, ctx=None)`` restore an equal representation.
"""
from __future__ import annotations

import numpy as np
import torch

from fwk.protocols import Representation, plays
from fwk.scaling import Scaler
from fwk.testing import build

from .metric import small_mesh


def small_batch(seed=0, b=6):
    """(b, 81, 3) noisy scaled copies of a bumpy 9 x 9 grid, and its Template."""
    V, t = small_mesh()
    rng = np.random.default_rng(seed)
    return np.stack([V * (1 + 0.05 * rng.normal()) + rng.normal(0, 0.01, V.shape) for _ in range(b)]), t


class RepresentationContract:
    component: type = None
    params: dict = {}
    atol: float = 1e-6

    def fitted(self, b=6):
        P, t = small_batch(b=b)
        r = build(self.component, self.params)
        r.fit(P, None, t)
        return r, P, t

    def test_declares_name_and_channels(self):
        assert isinstance(self.component.name, str) and self.component.name
        assert isinstance(self.component.channels, int) and self.component.channels > 0

    def test_plays_the_role_and_declares_placement(self):
        c = self.component
        assert plays(c, Representation), "the class must define every member of Representation"
        assert isinstance(c.places_rigidly, bool) and isinstance(c.relative_option, bool)
        r, P, t = self.fitted()
        assert isinstance(r, Representation) and isinstance(r.relative, bool)
        assert isinstance(r.scaler, Scaler), "scaler: the fwk.scaling.Scaler that encode applies last"
        if c.relative_option:  # the constructor takes `relative`
            assert build(self.component, {**self.params, "relative": True}).relative is True
            assert build(self.component, {**self.params, "relative": False}).relative is False
        if not r.places_rigidly:  # positions come back without a target
            assert np.allclose(r.decode(r.encode(P)), P, atol=self.atol)

    def test_shapes_and_round_trip(self):
        r, P, t = self.fitted()
        F = r.encode(P)
        assert F.shape == (len(P), P.shape[1], r.channels) and F.dtype == np.float32
        assert np.all(np.isfinite(F))
        X = r.decode(F, None, P)
        assert X.shape == P.shape and X.dtype == np.float64
        # relative representations (dr) lose position: the result is placed on the ground truth
        assert np.allclose(X, P, atol=self.atol)

    def test_batch_is_independent(self):
        r, P, t = self.fitted()
        F = r.encode(P)
        assert np.allclose(np.concatenate([r.encode(P[i:i + 1]) for i in range(len(P))]), F, atol=1e-6)

    def test_fit_on_small_data(self):
        r, P, t = self.fitted(b=2)
        assert np.all(np.isfinite(r.encode(P)))
        assert np.all(np.isfinite(r.decode(r.encode(P), None, P)))

    def test_unscale_is_differentiable_and_consistent(self):
        r, P, t = self.fitted()
        F = torch.tensor(r.encode(P), requires_grad=True)
        U = r.unscale(F)
        assert U.shape == F.shape
        U.sum().backward()
        assert F.grad is not None and torch.isfinite(F.grad).all()
        r0 = build(self.component, {**self.params, "scaling": "none"})
        r0.fit(P, None, t)
        assert np.allclose(U.detach().numpy(), r0.encode(P), atol=1e-4)

    def test_state_dict_round_trip(self):
        r, P, t = self.fitted()
        r2 = build(self.component, self.params)
        r2.load_state_dict(r.state_dict(), ctx=None)
        assert np.allclose(r2.encode(P), r.encode(P))
        assert np.allclose(r2.decode(r.encode(P), None, P), r.decode(r.encode(P), None, P))
