"""fwk.scaling.Scaler against naive loops over vertices and channels (DESIGN.md Definitions)."""
import numpy as np
import pytest
import torch

from fwk.errors import DataError, RecipeError
from fwk.scaling import Scaler


def _F(seed=0, b=7, n=5, c=3):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(b, n, c)) * rng.uniform(0.1, 3, size=(1, n, c)) + rng.normal(size=(1, n, c))


def test_std_per_vertex_and_per_channel_match_loops():
    F = _F()
    b, n, c = F.shape
    G = Scaler("std", "vertex").fit(F).transform(F)
    for i in range(n):
        for k in range(c):
            x = F[:, i, k]
            mu = sum(x) / b
            sd = (sum((v - mu) ** 2 for v in x) / b) ** 0.5
            assert np.allclose(G[:, i, k], (x - mu) / sd)
    G = Scaler("std", "channel").fit(F).transform(F)
    for k in range(c):
        x = F[..., k].ravel()
        mu = sum(x) / len(x)
        sd = (sum((v - mu) ** 2 for v in x) / len(x)) ** 0.5
        assert np.allclose(G[..., k], (F[..., k] - mu) / sd)


@pytest.mark.parametrize("a", [1.0, 0.5, 2.0])
def test_norm_matches_the_corrected_definition(a):
    F = _F(1)
    G = Scaler("norm", a=a).fit(F).transform(F)
    for k in range(F.shape[-1]):
        lo, hi = F[..., k].min(), F[..., k].max()
        assert np.allclose(G[..., k], (F[..., k] - lo) / (hi - lo) * 2 * a - a)
        assert G[..., k].min() == pytest.approx(-a) and G[..., k].max() == pytest.approx(a)


@pytest.mark.parametrize("kind,gran", [("none", "vertex"), ("std", "vertex"), ("std", "channel"), ("norm", "vertex")])
def test_inverses_and_state(kind, gran):
    F, H = _F(2), _F(3)  # H: data the scaler was not fitted on
    s = Scaler(kind, gran).fit(F)
    assert np.allclose(s.inverse(s.transform(H)), H)
    G = torch.tensor(s.transform(H), requires_grad=True)
    U = s.inverse_torch(G)
    assert np.allclose(U.detach().numpy(), H)
    (U ** 2).sum().backward()  # differentiable: d/dG (G div + shift)^2 = 2 U div
    assert np.allclose(G.grad.numpy(), 2 * H * np.broadcast_to(s.div, H.shape[1:]))
    t = Scaler().load_state_dict(s.state_dict())
    assert (t.kind, t.granularity) == (kind, gran) and np.array_equal(t.transform(H), s.transform(H))
    if kind == "none":
        assert np.array_equal(s.transform(H), H)


def test_constant_features_are_floored_not_divided_by_zero():
    F = _F(4)
    F[:, 2, 1] = 0.7  # a vertex that never moves
    F[..., 2] = 1.5  # a channel that never changes
    for kind, gran in [("std", "vertex"), ("std", "channel"), ("norm", "vertex")]:
        s = Scaler(kind, gran, eps=1e-6).fit(F)
        G = s.transform(F)
        assert np.all(np.isfinite(G)) and np.allclose(s.inverse(G), F)
        assert np.all(s.div >= 1e-6 / 2)


def test_errors():
    with pytest.raises(RecipeError, match="scaling.*std"):
        Scaler("sdt")
    with pytest.raises(RecipeError, match="granularity"):
        Scaler("std", "vertices")
    with pytest.raises(RecipeError, match="a > 0"):
        Scaler("norm", a=0)
    F = _F()
    F[0, 0, 0] = np.nan
    with pytest.raises(DataError, match="NaN"):
        Scaler("std").fit(F)
    with pytest.raises(RuntimeError, match="before fit"):
        Scaler("std").transform(_F())
