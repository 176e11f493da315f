"""The wrapped PyG conv passes fwk's conv contract suite, equals the bare PyG layer run on each
sample and GATv2's attention written out by hand, and trains inside ae, vae (fully convolutional
too) and dsm from a recipe; the shipped gatv2 recipes validate."""
from pathlib import Path

import numpy as np
import pytest
import torch
from torch_geometric.nn import GATv2Conv

from fwk.errors import RecipeError
from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import GenerativeModel, Hierarchy, Level, NetworkFactory
from fwk.recipes import load_recipe, resolve
from fwk.testing.conv import ConvContract
from fwk.testing.sampler import two_components
from fwk_example_plugin.gatv2 import GATv2, BatchedMessagePassing
from recipe_runs import assert_tested, assert_trained, run_recipe, tiny_recipe

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


class TestGATv2Contract(ConvContract):
    component = GATv2
    params = {"heads": 2}  # 16 and 8 output channels: two heads concatenated


class TestGATv2OnGraphLevelsContract(ConvContract):
    component = GATv2  # levels without faces (a connectivity-only sampler); heads averaged
    params = {"heads": 3, "concat": False}
    sampler = ("simple", {"levels": 2})


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("conv", "gatv2")
    assert e.component is GATv2 and e.plugin == "example-gatv2"


def _hierarchy():
    return get_registry().get("sampler", "quadric")(factors=[4]).build(two_components())


@pytest.mark.parametrize("heads, concat", [(1, None), (3, True), (3, False), (4, None)])
def test_batch_equals_the_bare_pyg_layer_on_each_sample(heads, concat):
    """The wrapper's (b, n, c) batch = PyG's own GATv2Conv (its default self-loop handling) on each
    sample's (n, c) features and the level's edge_index, one sample at a time."""
    h = _hierarchy()
    lv = h.levels[1]
    torch.manual_seed(0)
    conv = GATv2(5, 6, h, 1, heads=heads, concat=concat, negative_slope=0.1)
    cat = conv.concat
    bare = GATv2Conv(5, 6 // heads if cat else 6, heads=heads, concat=cat, negative_slope=0.1)  # add_self_loops
    bare.load_state_dict(conv.layer.state_dict())
    with torch.no_grad():
        bare.bias.normal_()
        conv.layer.bias.copy_(bare.bias)
    e = torch.as_tensor(np.r_[lv.edges, lv.edges[:, ::-1]].T.copy())  # both directions, no self loops
    x = torch.randn(3, lv.n_vertices, 5)
    y = conv(x)
    ref = torch.stack([bare(x[s], e) for s in range(len(x))])
    assert y.shape == (3, lv.n_vertices, 6)
    assert torch.allclose(y, ref, atol=1e-5)
    # another batch size: its own cached index, same per-sample values
    assert torch.allclose(conv(x[1:]), ref[1:], atol=1e-5)
    assert set(conv._batched) == {(3, torch.device("cpu")), (2, torch.device("cpu"))}


def _gatv2_by_hand(x, edges, n, Wl, bl, Wr, br, att, bias, heads, concat, slope):
    """GATv2 (Brody et al. 2022, eq. 7) written out with loops over vertices and their neighbours."""
    x = x.double().numpy()
    C = Wl.shape[0] // heads
    nb = {i: {i} for i in range(n)}  # self loops
    for a, b in edges:
        nb[a].add(b)
        nb[b].add(a)
    out = np.zeros((n, heads, C))
    for i in range(n):
        for hd in range(heads):
            rows = slice(hd * C, (hd + 1) * C)
            js = sorted(nb[i])
            e = []
            for j in js:
                s = Wr[rows] @ x[i] + br[rows] + Wl[rows] @ x[j] + bl[rows]
                s = np.where(s > 0, s, slope * s)
                e.append(att[hd] @ s)
            e = np.array(e)
            alpha = np.exp(e - e.max())
            alpha /= alpha.sum()
            for a, j in zip(alpha, js):
                out[i, hd] += a * (Wl[rows] @ x[j] + bl[rows])
    out = out.reshape(n, -1) if concat else out.mean(1)
    return out + bias


@pytest.mark.parametrize("concat", [True, False])
def test_attention_matches_a_hand_written_loop_over_edges(concat):
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [1, 3]])  # 4 vertices, one isolated (4)
    n = 5
    h = Hierarchy([Level(n_vertices=n, edges=edges)], [], [])
    torch.manual_seed(1)
    conv = GATv2(3, 4, h, 0, heads=2, concat=concat, negative_slope=0.3)
    with torch.no_grad():
        conv.layer.bias.normal_()
    p = {k: v.detach().double().numpy() for k, v in conv.layer.named_parameters()}
    x = torch.randn(2, n, 3)
    y = conv(x).detach().double().numpy()
    for s in range(2):
        ref = _gatv2_by_hand(x[s], edges, n, p["lin_l.weight"], p["lin_l.bias"], p["lin_r.weight"],
                             p["lin_r.bias"], p["att"][0], p["bias"], 2, concat, 0.3)
        assert np.allclose(y[s], ref, atol=1e-5)
    # the isolated vertex attends only to itself: its output is W_l x + b_l (+ b)
    x4 = x[0, 4].double().numpy()
    own = (p["lin_l.weight"] @ x4 + p["lin_l.bias"])
    own = own if concat else own.reshape(2, -1).mean(0)
    assert np.allclose(y[0, 4], own + p["bias"], atol=1e-5)


def test_generic_wrapper_runs_any_message_passing_layer():
    from torch_geometric.nn import SAGEConv

    from fwk.graph import edge_index

    lv = _hierarchy().levels[0]
    torch.manual_seed(0)
    layer = SAGEConv(3, 7)
    conv = BatchedMessagePassing(layer, edge_index(lv.edges, lv.n_vertices, self_loops=False), lv.n_vertices)
    x = torch.randn(2, lv.n_vertices, 3)
    e = edge_index(lv.edges, lv.n_vertices, self_loops=False)
    assert torch.allclose(conv(x), torch.stack([layer(x[s], e) for s in range(2)]), atol=1e-6)
    with pytest.raises(ValueError, match=r"expected \(b, "):
        conv(x[:, :-1])


def test_edge_index_is_a_buffer_that_moves_with_the_module():
    conv = GATv2(3, 4, _hierarchy(), 0)
    assert "edge_index" in dict(conv.named_buffers())
    assert "edge_index" not in conv.state_dict()  # derived from the hierarchy, not a checkpoint's
    conv(torch.randn(2, conv.n, 3))
    conv.double()  # _apply: the cached batched indices are dropped and rebuilt where used
    assert not conv._batched and conv(torch.randn(2, conv.n, 3, dtype=torch.float64)).dtype == torch.float64
    assert conv.edge_index.dtype == torch.long


@pytest.mark.parametrize("params, match", [
    ({"heads": 0}, "heads: at least one"),
    ({"heads": 3, "concat": True}, "heads: 3 heads do not divide 4"),
    ({"dropout": 1.0}, r"dropout: a probability in \[0, 1\)"),
    ({"negative_slope": -1.0}, "negative_slope: at least 0"),
])
def test_bad_parameters_are_recipe_errors(params, match):
    with pytest.raises(RecipeError, match=match):
        GATv2(3, 4, _hierarchy(), 0, **params)


def test_heads_concatenate_where_they_divide_and_average_otherwise():
    h = _hierarchy()
    assert GATv2(3, 8, h, 0, heads=4).concat and not GATv2(3, 3, h, 0, heads=4).concat
    assert GATv2(3, 3, h, 0, heads=4)(torch.randn(1, h.levels[0].n_vertices, 3)).shape[-1] == 3


RECIPE = tiny_recipe("""
ae: {name: ae, conv: {name: gatv2, heads: 2}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
vae: {name: vae, conv: {name: gatv2, heads: 2}, channels: [8, 16], latent: 8, sampler: {name: quadric, factors: [4, 4]}}
vae-fc: {name: vae, conv: {name: gatv2, heads: 2}, channels: [8, 16], latent: 8, sampler: {name: simple, levels: 2},
         fully_convolutional: true}
dsm: {name: dsm, k: 30, network: {name: vae, conv: {name: gatv2, heads: 2}, channels: [8, 16], latent: 8,
                                  sampler: {name: quadric, factors: [4, 4]}}}
""")


def test_gatv2_trains_in_ae_vae_fully_convolutional_vae_and_dsm(tmp_path, monkeypatch):
    run_dir = run_recipe(tmp_path, "gatv2.yaml", RECIPE, monkeypatch)
    metrics = assert_tested(run_dir, {"ae", "vae", "vae-fc", "dsm"}, only=True)
    assert_trained(run_dir, metrics, epochs=2)  # two epochs trained
    run = open_run(run_dir)  # the trained models reopen from the run directory, gatv2 layers and all
    for label in metrics:
        model = run.model(label)
        assert isinstance(model, GenerativeModel)
        S = model.sample(2, seed=0)
        assert S.ndim == 3 and S.shape[0] == 2 and np.isfinite(S).all()


@pytest.mark.parametrize("name", ["gatv2_ae.yaml", "gatv2_vae.yaml", "gatv2_dsm.yaml"])
def test_shipped_recipe_validates(name):
    """Each recipe the docs show resolves against the installed plugins (every key a parameter of
    its component, at any depth), its task and every model build, and the graph networks (the
    models themselves, or dsm's band networks) use gatv2; nothing loads or trains."""
    registry = get_registry()
    resolved = resolve(load_recipe(RECIPES / name), registry)
    assert resolved.task.name == "reconstruct" and resolved.train.epochs > 2
    task = resolved.task.build()
    assert task.dataset.name == "synthetic-heads"
    convs = []
    for label, spec in task.models.items():
        assert spec.build().name == spec.name, label
        net = spec.params.get("network")
        for s in ([spec] if net is None else [net]):
            if isinstance(s.build(), NetworkFactory):
                convs.append(s.params["conv"].name)
    assert convs and set(convs) == {"gatv2"}
