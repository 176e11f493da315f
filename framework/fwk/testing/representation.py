"""RepresentationContract: encode/decode round trip, shapes, differentiable unscale, state."""
from __future__ import annotations

import numpy as np


def small_batch(seed=0, b=6):
    from .metric import small_mesh

    V, t = small_mesh()
    rng = np.random.default_rng(seed)
    return np.stack([V * (1 + 0.05 * rng.normal()) + rng.normal(0, 0.01, V.shape) for _ in range(b)]), t


class RepresentationContract:
    component: type = None
    params: dict = {}
    atol: float = 1e-6

    def fitted(self):
        P, t = small_batch()
        r = self.component(**self.params)
        r.fit(P, None, t)
        return r, P, t

    def test_shapes_and_round_trip(self):
        r, P, t = self.fitted()
        F = r.encode(P)
        assert F.shape == (len(P), P.shape[1], r.channels) and F.dtype == np.float32
        # relative representations (dr) lose position: place the result on the ground truth
        assert np.allclose(r.decode(F, None, P), P, atol=self.atol)

    def test_unscale_is_differentiable_and_consistent(self):
        import torch

        r, P, t = self.fitted()
        F = torch.tensor(r.encode(P), requires_grad=True)
        U = r.unscale(F)
        U.sum().backward()
        assert F.grad is not None and torch.isfinite(F.grad).all()
        r0 = self.component(**{**self.params, "scaling": "none"})
        r0.fit(P, None, t)
        assert np.allclose(U.detach().numpy(), r0.encode(P), atol=1e-4)

    def test_state_dict_round_trip(self):
        r, P, t = self.fitted()
        r2 = self.component(**self.params)
        r2.load_state_dict(r.state_dict())
        assert np.allclose(r2.encode(P), r.encode(P))
