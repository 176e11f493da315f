"""feast: the reordered FeaStNet sums against torch_geometric's FeaStConv (the public
implementation) and a per-vertex loop, in value and gradient (input and every parameter), on
the irregular levels of the suite's two_components template; parameters and checkpoints as
FeaStConv's."""
import pytest
import torch
from torch.nn import functional as F
from torch_geometric.nn import FeaStConv

from fwk.errors import RecipeError
from fwk.graph import sparse_apply, torch_sparse
from fwk.plugins import get_registry
from fwk.testing.sampler import two_components

REG = get_registry()
FEAST = REG.get("conv", "feast")


@pytest.fixture(scope="module")
def hierarchy():
    return REG.get("sampler", "quadric")(factors=[4, 4]).build(two_components())


def perturbed(conv, seed=3):
    """Parameters moved off their initialisation (a non-zero c and bias of either sign, steering
    that varies between heads)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in conv.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=g))
    return conv


def pyg(conv, x):
    """torch_geometric's FeaStConv (with conv's parameters) on the batch as one graph of b n
    nodes, as a torch_geometric loader builds it."""
    b, n, c = x.shape
    ei = torch.cat([conv.edges + k * n for k in range(b)], 1)
    return conv.conv(x.reshape(b * n, c), ei).reshape(b, n, -1)


def loop(conv, x, nbrs):
    """A per-vertex loop of the formula: y_i = b + 1/|N_i| sum_{j in N_i} sum_h q_h(i, j) W_h x_j,
    q(i, j) = softmax_h(u_h . (x_j - x_i) + c_h), N_i the neighbours with i itself."""
    H, co = conv.heads, conv.conv.out_channels
    W = conv.conv.lin.weight.view(H, co, -1)
    U, c, bias = conv.conv.u.weight, conv.conv.c, conv.conv.bias
    out = []
    for i, N in enumerate(nbrs):
        acc = 0
        for j in N:
            q = torch.softmax((x[:, j] - x[:, i]) @ U.t() + c, -1)        # (b, H)
            acc = acc + torch.einsum("bh,hoc,bc->bo", q, W, x[:, j])
        out.append(acc / len(N) + bias)
    return torch.stack(out, 1)


def grads(f, x, conv):
    y = f(x)
    g = torch.randn(y.shape, generator=torch.Generator().manual_seed(7)).to(y.device)
    return y, torch.autograd.grad((y * g).sum(), [x, *conv.parameters()])


def close(a, b, tol=2e-5):
    return (a - b).abs().max() <= tol * (1 + b.abs().max())


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("heads", [1, 8])
@pytest.mark.parametrize("c_in,c_out", [(3, 16), (24, 2)])
@pytest.mark.parametrize("order", ["auto", "aggregate", "transform"])
def test_equals_torch_geometric_feastconv(hierarchy, threads, heads, c_in, c_out, order):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for level in (0, 1):
            torch.manual_seed(0)
            conv = perturbed(FEAST(c_in, c_out, hierarchy, level, heads=heads, order=order))
            x = torch.randn(3, hierarchy.levels[level].n_vertices, c_in, requires_grad=True)
            y, got = grads(conv, x, conv)
            e, ref = grads(lambda v: pyg(conv, v), x, conv)
            assert y.shape == e.shape and close(y, e), (level, float((y - e).abs().max()))
            for name, a, b in zip(["x", *dict(conv.named_parameters())], got, ref):
                assert close(a, b), (level, name, float((a - b).abs().max()), float(b.abs().max()))
    finally:
        torch.set_num_threads(before)


def test_orders_are_chosen_by_the_cheaper_per_edge_width(hierarchy):
    assert FEAST(3, 16, hierarchy, 0).order == "aggregate"
    assert FEAST(128, 64, hierarchy, 0).order == "aggregate"  # H c_out = 512 > 128 (heads 8)
    assert FEAST(64, 4, hierarchy, 0).order == "transform"    # H c_out = 32 < 64
    assert FEAST(16, 3, hierarchy, 0, heads=1).order == "transform"
    with pytest.raises(RecipeError, match="order"):
        FEAST(3, 4, hierarchy, 0, order="fast")


@pytest.mark.parametrize("order", ["aggregate", "transform"])
def test_equals_a_per_vertex_loop_on_an_irregular_level(hierarchy, order):
    level = 2  # the coarsest level: few vertices, neighbourhoods of 3 to 9
    lv = hierarchy.levels[level]
    nbrs = [[i] for i in range(lv.n_vertices)]
    for a, b in lv.edges:
        if a != b:
            nbrs[int(a)].append(int(b))
            nbrs[int(b)].append(int(a))
    assert len({len(N) for N in nbrs}) >= 3, "the test wants irregular neighbourhoods"
    torch.manual_seed(1)
    conv = perturbed(FEAST(5, 7, hierarchy, level, heads=8, order=order))
    x = torch.randn(2, lv.n_vertices, 5, requires_grad=True)
    y, got = grads(conv, x, conv)
    e, ref = grads(lambda v: loop(conv, v, nbrs), x, conv)
    assert close(y, e)
    for a, b in zip(got, ref):
        assert close(a, b)


def test_far_apart_logits_fall_back_to_a_plain_softmax(hierarchy):
    """Steering logits 100s apart between heads: the per-vertex factors exp(s) would underflow
    their products; those rows are recomputed and still match FeaStConv."""
    torch.manual_seed(2)
    conv = FEAST(4, 6, hierarchy, 0, heads=8)
    with torch.no_grad():
        conv.conv.u.weight.mul_(400.0)
    x = torch.randn(2, hierarchy.levels[0].n_vertices, 4, requires_grad=True)
    y, got = grads(conv, x, conv)
    e, ref = grads(lambda v: pyg(conv, v), x, conv)
    assert torch.isfinite(y).all() and close(y, e)
    for a, b in zip(got, ref):
        assert close(a, b, 1e-4)


def test_parameters_initialisation_and_checkpoints_are_feastconvs(hierarchy):
    torch.manual_seed(5)
    conv = FEAST(3, 16, hierarchy, 0, heads=8)
    torch.manual_seed(5)
    ref = FeaStConv(3, 16, heads=8, add_self_loops=True)
    assert set(conv.state_dict()) == {"edges", "conv.lin.weight", "conv.u.weight", "conv.c", "conv.bias"}
    for k, v in ref.state_dict().items():  # the same random draws in the same order
        assert torch.equal(conv.state_dict()[f"conv.{k}"], v), k
    # a checkpoint of the module as it was (FeaStConv's own forward: order "edges") loads and
    # gives the same outputs
    torch.manual_seed(6)
    old = perturbed(FEAST(3, 16, hierarchy, 0, heads=8, order="edges"))
    conv.load_state_dict(old.state_dict())
    x = torch.randn(2, hierarchy.levels[0].n_vertices, 3)
    assert close(conv(x), old(x))
    assert not old.fuses_pooling and conv.fuses_pooling  # the old order runs the model's plain pooling


@pytest.mark.parametrize("order", ["aggregate", "transform"])
def test_fused_pooling_in_both_orders(hierarchy, order):
    """forward(x, rows=kept) = D forward(x), forward_up(x, U) = forward(U x) (transform: the
    products on the coarse vertices), values and gradients."""
    D, U = torch_sparse(hierarchy.down[0]).coalesce(), torch_sparse(hierarchy.up[0])
    kept = D.indices()[1]
    torch.manual_seed(4)
    conv = perturbed(FEAST(6, 5, hierarchy, 0, heads=8, order=order))
    for fused, plain, n_in in ((lambda v: conv(v, rows=kept), lambda v: sparse_apply(D, conv(v)), hierarchy.levels[0].n_vertices),
                               (lambda v: conv.forward_up(v, U), lambda v: conv(sparse_apply(U, v)), hierarchy.levels[1].n_vertices)):
        x = torch.randn(3, n_in, 6, requires_grad=True)
        y, got = grads(fused, x, conv)
        e, ref = grads(plain, x, conv)
        assert close(y, e)
        for a, b in zip(got, ref):
            assert close(a, b)


def test_bfloat16_autocast_runs_in_float32(hierarchy):
    conv = perturbed(FEAST(3, 8, hierarchy, 0))
    x = torch.randn(2, hierarchy.levels[0].n_vertices, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = conv(x)
    assert y.dtype == torch.float32 and close(y, conv(x))


def test_cuda_matches_cpu_when_available(hierarchy):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device on this machine")
    torch.manual_seed(0)
    conv = perturbed(FEAST(3, 16, hierarchy, 0))
    x = torch.randn(2, hierarchy.levels[0].n_vertices, 3, requires_grad=True)
    y, got = grads(conv, x, conv)
    xc = x.detach().cuda().requires_grad_()
    gpu = conv.cuda()
    yc, gotc = grads(gpu, xc, gpu)
    assert close(yc.cpu(), y)
    for a, b in zip(gotc, got):
        assert close(a.cpu(), b)


def test_elu_network_step_is_finite(hierarchy):
    """Two convs and an ELU in a row, backward through both (the AE's pattern)."""
    a, b = FEAST(3, 16, hierarchy, 0), FEAST(16, 3, hierarchy, 0)
    x = torch.randn(2, hierarchy.levels[0].n_vertices, 3)
    loss = b(F.elu(a(x))).abs().mean()
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in [*a.parameters(), *b.parameters()])


def test_autoencoder_trains_as_with_feastconv():
    """The thesis's FeaStNet AE layout (pooling fused into the convs) against the same AE on
    FeaStConv's own forward (order "edges", pooling after each conv), from the same seed: the
    same losses over a few Adam steps."""
    from fwk.recipes import make_spec

    template = two_components()
    x = torch.randn(4, template.n_vertices, 3, generator=torch.Generator().manual_seed(0))
    losses = {}
    for order in ("edges", "auto"):
        spec = {"name": "ae", "conv": {"name": "feast", "heads": 8, "order": order}, "channels": [8, 16],
                "latent": 8, "sampler": {"name": "quadric", "factors": [4, 4]}}
        torch.manual_seed(0)
        m = make_spec("model", spec, "model", REG).build()
        enc, dec = m.build_encoder(template, 3), m.build_decoder(template, 3)
        assert all(c.fuses_pooling == (order == "auto") for c in [*enc.convs, *dec.convs])
        opt = torch.optim.Adam([*enc.parameters(), *dec.parameters()], 1e-3)
        losses[order] = []
        for _ in range(4):
            opt.zero_grad()
            loss = (dec(enc(x)[0]) - x).abs().mean()
            loss.backward()
            opt.step()
            losses[order].append(loss.item())
    assert losses["auto"][0] == pytest.approx(losses["edges"][0], rel=1e-6)
    assert losses["auto"] == pytest.approx(losses["edges"], rel=1e-4)
    assert losses["auto"][-1] < losses["auto"][0]


@pytest.mark.parametrize("init, expected", [("feastconv", 1 / 24), ("variance", 1.0)])
def test_init_variance_of_a_smooth_field(hierarchy, init, expected):
    """At initialisation, for a feature field constant over the mesh (a decoder's up-sampled
    features vary slowly between neighbours) with independent unit-variance channels, var(x' - b)
    / var(x) is 1/(3H) with FeaStConv's draw and 1 with init=variance (H = 8), measured over 128
    fields and 4 draws of the weights; forward still equals torch_geometric's FeaStConv."""
    n = hierarchy.levels[0].n_vertices
    ratios = []
    for seed in range(4):
        torch.manual_seed(seed)
        conv = FEAST(32, 32, hierarchy=hierarchy, level=0, heads=8, init=init)
        z = torch.randn(128, 1, 32, generator=torch.Generator().manual_seed(10 + seed))
        x = z.expand(128, n, 32).contiguous()
        with torch.no_grad():
            y = conv(x) - conv.conv.bias
            if seed == 0:
                assert torch.allclose(y[:4] + conv.conv.bias, pyg(conv, x[:4]), atol=1e-5)
        ratios.append(float(y.var(0).mean() / x.var(0).mean()))
    assert expected * 0.8 < sum(ratios) / 4 < expected * 1.25, ratios


def test_init_variance_survives_reset_and_is_checked(hierarchy):
    torch.manual_seed(0)
    plain = FEAST(8, 8, hierarchy=hierarchy, level=0)
    torch.manual_seed(0)
    scaled = FEAST(8, 8, hierarchy=hierarchy, level=0, init="variance")
    assert torch.allclose(scaled.conv.lin.weight, plain.conv.lin.weight * 24 ** 0.5)
    assert torch.equal(scaled.conv.u.weight, plain.conv.u.weight)
    torch.manual_seed(1)
    plain.reset_parameters()
    torch.manual_seed(1)
    scaled.reset_parameters()
    assert torch.allclose(scaled.conv.lin.weight, plain.conv.lin.weight * 24 ** 0.5)
    with pytest.raises(RecipeError, match="init must be one of feastconv, variance, not 'kaiming'"):
        FEAST(8, 8, hierarchy=hierarchy, level=0, init="kaiming")
