"""The fully convolutional latent (n latent vertices x c features) of the vcconv VAE."""
from collections import deque

import numpy as np
import pytest
import torch

from fwk.errors import RecipeError
from fwk.plugins import get_registry
from fwk.testing.model import tiny_fit_data
from fwk.testing.sampler import two_components
from fwk_autoencoder.latent import farthest_centres, latent_support, with_latent_level

REG = get_registry()


def _bfs(nbrs, s):
    d = {s: 0}
    q = deque([s])
    while q:
        u = q.popleft()
        for w in nbrs[u]:
            if w not in d:
                d[w] = d[u] + 1
                q.append(w)
    return d


def _naive(edges, n, k, radius):
    nbrs = [[] for _ in range(n)]
    for a, b in edges:
        nbrs[a].append(b)
        nbrs[b].append(a)
    C, best = [0], [np.inf] * n
    while len(C) < k:
        d = _bfs(nbrs, C[-1])
        best = [-1 if v in C else min(best[v], d.get(v, np.inf)) for v in range(n)]
        C.append(max(range(n), key=lambda v: (best[v], -v)))
    dists = [_bfs(nbrs, c) for c in C]
    P = np.zeros((k, n), bool)
    for v in range(n):
        ds = [dd.get(v, np.inf) for dd in dists]
        if np.isfinite(min(ds)):
            P[int(np.argmin(ds)), v] = True
        for i, dd in enumerate(dists):
            if dd.get(v, np.inf) <= radius:
                P[i, v] = True
    return C, P


def _level(levels=2):
    t = two_components()
    return t, REG.get("sampler", "simple")(levels=levels).build(t, None)


@pytest.mark.parametrize("k,radius", [(5, 1), (8, 2)])
def test_latent_support_against_loops(k, radius):
    _, h = _level()
    lv = h.levels[2]
    C, P = latent_support(lv, k, radius)
    Cn, Pn = _naive(lv.edges, lv.n_vertices, k, radius)
    assert list(C) == Cn
    assert np.array_equal(P.toarray() > 0, Pn)


def test_latent_level_covers_every_vertex_and_both_components():
    _, h = _level()
    H = with_latent_level(h, 2, 6)
    assert [lv.n_vertices for lv in H.levels] == [h.levels[0].n_vertices, h.levels[1].n_vertices, 6]
    D, U = H.down[-1].toarray(), H.up[-1].toarray()
    assert np.allclose(D.sum(1), 1) and np.allclose(U.sum(1), 1)  # every vertex pooled, every centre fed
    n0 = h.levels[1].n_vertices
    from scipy.sparse.csgraph import connected_components

    from fwk.graph import adjacency

    _, lab = connected_components(adjacency(h.levels[1].edges, n0))
    assert len(set(lab[H.levels[2].centres])) == 2  # a centre on each component
    assert H.levels[1] is not h.levels[1] and h.levels[2].n_vertices != 6  # the (cached) input is not changed
    assert H.levels[1].unpool.index.shape[0] == n0


def test_too_few_vertices_or_levels_is_a_recipe_error():
    _, h = _level()
    with pytest.raises(RecipeError, match="latent_vertices"):
        with_latent_level(h, 2, h.levels[1].n_vertices + 1)
    with pytest.raises(RecipeError, match="latent_vertices"):
        with_latent_level(h, 5, 4)


def test_centres_fall_in_unreached_components_first():
    import scipy.sparse as sp

    A = sp.csr_matrix(np.array([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]], float))
    assert list(farthest_centres(A, 2)) == [0, 2]


def _vae(**kw):
    from fwk.recipes import make_spec

    spec = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 6}, "sampler": {"name": "simple", "levels": 2},
            "channels": [8, 8, 4], "latent_vertices": 5, **kw}
    return make_spec("model", spec, "model", REG).build()


def test_latent_vertices_vae_encoder_decoder_shapes_and_composition():
    data = tiny_fit_data()
    t = data.template
    m = _vae()
    assert m.latent == 20  # 5 latent vertices x 4 features
    enc, dec = m.build_encoder(t, 9), m.build_decoder(t, 3)
    lin = [x for x in enc.modules() if isinstance(x, torch.nn.Linear)]
    assert all(max(x.in_features, x.out_features) <= 9 for x in lin)  # only residual channel maps: no FC latent
    x = torch.randn(2, t.n_vertices, 9)
    mu, logvar = enc(x)
    assert mu.shape == logvar.shape == (2, 20)
    assert dec(mu).shape == (2, t.n_vertices, 3)
    assert m.build_decoder(t, 3, latent_in=33)(torch.randn(2, 33)).shape == (2, t.n_vertices, 3)
    assert m.hierarchy.levels[-1].n_vertices == 5


def test_latent_vertices_vae_learns(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from fwk.runs import make_test_context

    data = tiny_fit_data(n_subjects=24)
    ctx = make_test_context(tmp_path, epochs=25, batch_size=8, lr=1e-3)
    m = _vae(channels=[16, 16, 8])
    m.fit(data, ctx)
    (d,) = {p.parent for p in (ctx.run_dir / "tb").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    loss = [e.value for e in ea.Scalars("train_l1")]
    assert loss[-1] < 0.7 * loss[0], loss
    P = data.stack("val")
    R = m.reconstruct(P)
    assert R.shape == P.shape and np.isfinite(R).all()
    m2 = _vae(channels=[16, 16, 8])
    m2.load_state_dict(m.state_dict())
    assert np.allclose(m2.reconstruct(P), R, atol=1e-5)
