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


# ---------------------------------------------------------------------------- issue 17: granularity,
# robust range and centring of norm, each against a naive loop over vertices and channels

def _naive_lo_hi(x, rng, q):
    """Min / max, or the q and 1 - q quantiles by sorting and interpolating linearly (numpy's
    default method, written out)."""
    if rng == "minmax":
        return min(x), max(x)
    s = sorted(x)

    def quant(p):
        h = (len(s) - 1) * p
        lo = int(np.floor(h))
        hi = min(lo + 1, len(s) - 1)
        return s[lo] + (h - lo) * (s[hi] - s[lo])
    return quant(q), quant(1 - q)


def _naive_norm(F, gran, rng, centre, a, q):
    """The norm of fwk.scaling written as loops: per (vertex, channel) or per channel."""
    b, n, c = F.shape
    G = np.empty_like(F)
    for k in range(c):
        for i in range(n):
            mean_i = sum(F[:, i, k]) / b
            if gran == "vertex":
                pool = list(F[:, i, k] - (mean_i if centre == "mean" else 0.0))
            else:
                pool = [F[s, v, k] - (sum(F[:, v, k]) / b if centre == "mean" else 0.0) for s in range(b) for v in range(n)]
            lo, hi = _naive_lo_hi(pool, rng, q)
            for s in range(b):
                if centre == "mid":
                    G[s, i, k] = (F[s, i, k] - lo) / (hi - lo) * 2 * a - a
                else:
                    G[s, i, k] = (F[s, i, k] - mean_i) / max(hi, -lo) * a
    return G


@pytest.mark.parametrize("gran", ["vertex", "channel"])
@pytest.mark.parametrize("rng", ["minmax", "quantile"])
@pytest.mark.parametrize("centre", ["mid", "mean"])
def test_norm_options_match_naive_loops(gran, rng, centre):
    F = _F(5, b=9, n=4, c=2)
    a, q = 0.7, 0.1
    s = Scaler("norm", gran, a=a, range=rng, q=q, centre=centre).fit(F)
    assert np.allclose(s.transform(F), _naive_norm(F, gran, rng, centre, a, q), rtol=1e-12, atol=1e-12)
    assert s.shift.shape == ((F.shape[1] if gran == "vertex" or centre == "mean" else 1), F.shape[2])


@pytest.mark.parametrize("gran", ["vertex", "channel"])
def test_quantile_range_is_numpys(gran):
    F = _F(6, b=40, n=6, c=3)
    F[3, 2, 1] = 1e3  # an outlier: min-max would let it set the range, the quantile range does not
    s = Scaler("norm", gran, range="quantile", q=0.05).fit(F)
    axes = (0,) if gran == "vertex" else (0, 1)
    lo = np.quantile(F, 0.05, axis=axes).reshape(-1, 3)
    hi = np.quantile(F, 0.95, axis=axes).reshape(-1, 3)
    assert np.allclose(s.shift, (lo + hi) / 2) and np.allclose(s.div, (hi - lo) / 2)
    G = s.transform(F)
    assert G[3, 2, 1] > 10  # not clipped: beyond [-1, 1], and still invertible
    assert np.allclose(s.inverse(G), F)
    inside = np.mean(np.abs(G) <= 1 + 1e-12)
    assert inside >= 0.85


@pytest.mark.parametrize("kind,gran", [("norm", "vertex"), ("norm", "channel"), ("std", "vertex"), ("std", "channel")])
@pytest.mark.parametrize("rng", ["minmax", "quantile"])
def test_zero_decodes_to_the_training_mean_exactly(kind, gran, rng):
    F = _F(7)
    s = Scaler(kind, gran, range=rng, centre="mean").fit(F)
    if kind == "norm" or gran == "vertex":  # std per channel centres on the channel's mean
        assert np.array_equal(s.inverse(np.zeros_like(F)), np.broadcast_to(F.mean(axis=0), F.shape))
    G = s.transform(F)
    if kind == "norm" and rng == "minmax":  # the training range still lies in [-a, a], one side touching
        assert np.abs(G).max() == pytest.approx(1.0)
        assert np.all(np.abs(G) <= 1 + 1e-12)
    H = _F(8)
    assert np.allclose(s.inverse(s.transform(H)), H, rtol=1e-13, atol=1e-13)
    t = Scaler().load_state_dict(s.state_dict())
    assert (t.kind, t.granularity, t.range, t.centre) == (kind, gran, rng, "mean")
    assert np.array_equal(t.transform(H), s.transform(H))


def test_granularity_default_is_the_kinds_own_and_norm_honours_it():
    F = _F(9)
    assert Scaler("std").granularity == "vertex" and Scaler("norm").granularity == "channel"
    assert Scaler("norm").fit(F).shift.shape == (1, 3)  # as before issue 17
    assert Scaler("norm", "vertex").fit(F).shift.shape == (F.shape[1], 3)  # no longer ignored


def test_old_state_loads_as_what_it_was():
    F, H = _F(10), _F(11)
    c = F.shape[-1]
    lo, hi = F.min(axis=(0, 1)).reshape(1, c), F.max(axis=(0, 1)).reshape(1, c)
    # what Scaler("norm", "vertex").state_dict() held before issue 17 (norm was per channel whatever its granularity)
    old = {"kind": "norm", "granularity": "vertex", "a": 1.0, "eps": 1e-8, "shift": lo + (hi - lo) / 2, "div": (hi - lo) / 2}
    s = Scaler("norm", "vertex", range="quantile", centre="mean").load_state_dict(old)
    assert (s.granularity, s.range, s.centre) == ("channel", "minmax", "mid")
    assert np.allclose(s.transform(H), (H - lo) / (hi - lo) * 2 - 1)
    assert np.array_equal(s.transform(H), Scaler("norm").fit(F).transform(H))


def test_option_errors():
    with pytest.raises(RecipeError, match="range"):
        Scaler("norm", range="robust")
    with pytest.raises(RecipeError, match="centre"):
        Scaler("norm", centre="median")
    with pytest.raises(RecipeError, match="q"):
        Scaler("norm", range="quantile", q=0.5)


@pytest.mark.parametrize("settings", [
    dict(kind="std", granularity="vertex"), dict(kind="std", granularity="channel"),
    dict(kind="norm", granularity="channel"), dict(kind="norm", granularity="vertex", a=2.0),
    dict(kind="norm", granularity="vertex", range="quantile", q=0.1, centre="mean"), dict(kind="none")])
def test_like_composes_into_the_scaling_fitted_on_raw_features(settings):
    """Scaler.like(s) fitted on features s already scaled, applied after s, equals the scaling of
    s's settings fitted on the raw features of that group (pb's per-expression scaling)."""
    pooled = _F(seed=1, b=20)
    group = pooled[:6] * 0.3 + 0.1  # a group whose statistics differ from the pool's
    s = Scaler(**settings).fit(np.concatenate([pooled, group]))
    again = Scaler.like(s)
    assert (again.kind, again.granularity, again.a, again.eps, again.range, again.q, again.centre) == \
        (s.kind, s.granularity, s.a, s.eps, s.range, s.q, s.centre) and again.shift is None
    again.fit(s.transform(group))
    direct = Scaler(**settings).fit(group)
    test = _F(seed=2, b=4) * 0.3
    assert np.allclose(again.transform(s.transform(test)), direct.transform(test), atol=1e-9)
    G = direct.transform(test)
    assert np.allclose(s.inverse(again.inverse(G)), direct.inverse(G), atol=1e-9)
