import pytest

from fwk.plugins import get_registry
from fwk.testing.conv import ConvContract

REG = get_registry()


class TestSpiralContract(ConvContract):
    component = REG.get("conv", "spiral")
    params = {"length": 9, "dilation": 2}


class TestSpiralDefaultsContract(ConvContract):
    component = REG.get("conv", "spiral")  # Neural 3DMM defaults: 2 rings, dilation 2, mean + 2 std


class TestFeaStContract(ConvContract):
    component = REG.get("conv", "feast")
    params = {"heads": 4}


class TestLSAContract(ConvContract):
    component = REG.get("conv", "lsa")


class TestLSATinyContract(ConvContract):
    component = REG.get("conv", "lsa")
    params = {"basis": 4}


def test_lsa_starts_as_a_plain_neighbourhood_linear_layer():
    import torch

    from fwk.testing.sampler import two_components

    h = REG.get("sampler", "quadric")(factors=[4]).build(two_components())
    for params in ({}, {"basis": 4}):
        conv = REG.get("conv", "lsa")(3, 5, h, 1, **params)
        x = torch.randn(2, h.levels[1].n_vertices, 3)
        ref = conv.layer(x[:, conv.index].reshape(2, -1, conv.k * 3))
        assert torch.allclose(conv(x), ref, atol=1e-5)  # A_i = I at initialisation


def test_lsa_matches_a_per_vertex_loop_and_tiny_weights_vary_per_vertex():
    import torch

    from fwk.testing.sampler import two_components

    h = REG.get("sampler", "quadric")(factors=[4, 4]).build(two_components())
    lv = h.levels[1]
    conv = REG.get("conv", "lsa")(3, 5, h, 1)
    with torch.no_grad():
        conv.A.add_(0.3 * torch.randn_like(conv.A))
    x = torch.randn(2, lv.n_vertices, 3)
    y = conv(x)
    idx = conv.index.reshape(lv.n_vertices, conv.k)
    nb = {i: sorted({int(b) for a, b in lv.edges if a == i} | {int(a) for a, b in lv.edges if b == i}) for i in (0, 5, 17)}
    for i in nb:
        assert list(idx[i]) == ([i] + nb[i] + [i] * 9)[:9]  # the vertex, its first 8 adjacency entries, padding
        Xi = x[1, idx[i]]                                    # (K, c)
        ref = conv.layer.weight @ (conv.A[i].T @ Xi).reshape(-1) + conv.layer.bias
        assert torch.allclose(y[1, i], ref, atol=1e-5)
    tiny = REG.get("conv", "lsa")(3, 5, h, 1, basis=8)
    assert tiny.tiny and tiny.A is None
    with torch.no_grad():
        tiny.bases.add_(0.3 * torch.randn_like(tiny.bases))
    W = tiny.weights()
    assert W.shape == (lv.n_vertices, 9, 9) and (W[0] - W[1]).abs().max() > 1e-4
    small = REG.get("conv", "lsa")(3, 5, h, 2, basis=8)  # at most 128 vertices: a free A_i
    assert h.levels[2].n_vertices <= 128 and small.A is not None


# FeaStNet's feature-steered assignments start near uniform: its loss plateaus for ~40 steps
# before it falls, so it gets more epochs (measured: 0.797 -> 0.437 in 150 full-batch steps)
@pytest.mark.parametrize("conv,epochs", [("spiral", 12), ("feast", 50), ("lsa", 12)])
def test_each_conv_autoencoder_learns(tmp_path, conv, epochs):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from fwk.recipes import make_spec
    from fwk.runs import make_test_context
    from fwk.testing.model import tiny_fit_data

    data = tiny_fit_data(n_subjects=24)
    ctx = make_test_context(tmp_path, epochs=epochs, batch_size=8, lr=1e-3)
    m = make_spec("model", {"name": "ae", "conv": conv, "channels": [8, 16], "latent": 8,
                            "sampler": {"name": "quadric", "factors": [4, 4]}}, "model", REG).build()
    m.fit(data, ctx)
    (d,) = {p.parent for p in (ctx.run_dir / "tb").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    loss = [e.value for e in ea.Scalars("train_l1")]
    assert loss[-1] < 0.7 * loss[0], loss


class TestVCConvContract(ConvContract):
    component = REG.get("conv", "vcconv")
    params = {"weight_num": 6}
    sampler = ("simple", {"levels": 2})


class TestVCConvOnQuadric(ConvContract):
    component = REG.get("conv", "vcconv")
    params = {"weight_num": 6, "radius": 1, "residual_rate": 0.5}


def test_vcconv_strided_and_transposed_shapes_and_naive_reference():
    import torch

    from fwk.testing.sampler import two_components

    h = REG.get("sampler", "simple")(levels=2).build(two_components())
    VC = REG.get("conv", "vcconv")
    down = VC(3, 5, h, 0, weight_num=4, mode="down", residual_rate=0.5)
    up = VC(5, 3, h, 0, weight_num=4, mode="up", residual_rate=0.5)
    x = torch.randn(2, h.levels[0].n_vertices, 3)
    z = down(x)
    assert z.shape == (2, h.levels[1].n_vertices, 5)
    assert up(z).shape == x.shape
    # naive: y_i = b + sum_j sum_m A_ijm B_m^T x_j over the pool neighbourhood of centre i
    plain = VC(3, 5, h, 0, weight_num=4, mode="down")
    y = plain(x)
    idx, mask = h.levels[1].pool.index, h.levels[1].pool.mask
    for i in (0, 7):
        acc = plain.bias.clone()
        for k in range(idx.shape[1]):
            if mask[i, k]:
                W = sum(plain.padded(plain.coef)[i, k, m] * plain.basis[m] for m in range(4))
                acc = acc + x[1, idx[i, k]] @ W
        assert torch.allclose(y[1, i], acc, atol=1e-5)


def test_the_device_check_passes_a_conv_and_catches_a_device_dependent_one():
    """``assert_cuda_matches_cpu`` with the CPU as the 'other' device (no GPU needed): a conv
    passes; a module whose copy computes differently fails on the value."""
    import torch

    from fwk.testing.conv import assert_cuda_matches_cpu

    t = TestVCConvOnQuadric()
    h = t.hierarchy()
    assert_cuda_matches_cpu(t.make(3, 8, 0, hierarchy=h), lambda c: c, torch.randn(2, h.levels[0].n_vertices, 3),
                            device="cpu")

    class Drifting(torch.nn.Linear):  # each copy adds its own offset
        def __deepcopy__(self, memo):
            other = Drifting(self.in_features, self.out_features)
            other.load_state_dict(self.state_dict())
            other.offset = 1.0
            return other

        offset = 0.0

        def forward(self, x):
            return super().forward(x) + self.offset

    with pytest.raises(AssertionError, match="tensor 0"):
        assert_cuda_matches_cpu(Drifting(3, 4), lambda m: m, torch.randn(5, 3), device="cpu")


@pytest.mark.parametrize("mode,residual", [("down", 0.5), ("up", 0.5), ("same", None), ("down", None)])
def test_vcconv_reads_the_padded_coefficients_of_earlier_versions(mode, residual):
    """Before 2026-12-07 ``coef`` was (n_out, K, M) and ``res_w`` (n_out, K), padded to the largest
    support; today they hold the valid (i, k) pairs only. A state dict in the padded layout (the
    padding filled with noise, which no order read) loads into today's conv, which then computes
    what the conv it came from did; the initial draws are the padded layout's at the valid pairs."""
    import torch

    from fwk.testing.sampler import two_components

    h = REG.get("sampler", "simple")(levels=3).build(two_components())
    torch.manual_seed(0)
    conv = REG.get("conv", "vcconv")(4, 5, h, 1, weight_num=6, mode=mode, residual_rate=residual)
    M, mask = 6, conv.mask.bool()
    assert conv.coef.shape == (int(mask.sum()), M) and conv.n_slots < conv.n_out * conv.K
    torch.manual_seed(0)
    torch.randn(conv.basis.shape)  # reset_parameters' draws: the basis, then every (i, k)'s coefficients
    assert torch.equal(conv.padded(conv.coef), (torch.randn(conv.n_out, conv.K, M) / M ** 0.5) * mask[..., None])
    old = {k: v.clone() for k, v in conv.state_dict().items()}
    old["coef"] = conv.padded(conv.coef.detach()) + torch.randn(conv.n_out, conv.K, M) * ~mask[..., None]
    if conv.res_w is not None:
        with torch.no_grad():
            conv.res_w.uniform_(0.1, 2.0)
        old["res_w"] = conv.padded(conv.res_w.detach()) + 5 * ~mask
    x = torch.randn(3, conv.n_in, 4)
    expected = conv(x)
    torch.manual_seed(1)
    fresh = REG.get("conv", "vcconv")(4, 5, h, 1, weight_num=6, mode=mode, residual_rate=residual)
    fresh.load_state_dict(old)
    assert torch.equal(fresh.coef, conv.coef) and torch.allclose(fresh(x), expected, atol=1e-6)
    assert torch.equal(fresh.upgrade("coef", old["coef"]), conv.coef.detach())
    assert fresh.upgrade("basis", old["basis"]) is old["basis"]
