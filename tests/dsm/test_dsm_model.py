"""Deep Spectral Meshes: the reconstruction and band-model contracts, exact assembly with perfect
decoders, the conditioning mask, one optimiser per band, deterministic sampling, three bands, the
nested components as recipe parameters."""
import numpy as np
import pytest
import torch

from fwk.data.preprocess import Preprocessor
from fwk.errors import RecipeError
from fwk.plugins import get_registry
from fwk.protocols import FitData
from fwk.recipes import make_spec
from fwk.runs import make_test_context
from fwk.safeio import load_state, save_state
from fwk.testing.generative import BandModelContract
from fwk.testing.model import ModelContract

REG = get_registry()
NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
# the thesis's layout (4.4.3) in small: vcconv, residual blocks, 5 latent vertices x 4 channels per band
LATENT_NET = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 6}, "sampler": {"name": "simple", "levels": 2},
              "channels": [8, 8, 4], "latent_vertices": 5, "residual_rate": 0.5}


def _dsm(**params):
    """A dsm model built as a recipe builds it (nested components resolved to specs)."""
    return make_spec("model", {"name": "dsm", **params}, "dsm", REG).build()


class TestDSMContract(ModelContract):
    component = REG.get("model", "dsm")
    params = {"network": NET, "k": 20, "gamma": 0.5}


class TestDSMBands(BandModelContract):
    component = REG.get("model", "dsm")
    params = {"network": NET, "k": [10, 40]}


class TestLatentMapDSMBands(BandModelContract):
    component = REG.get("model", "dsm")
    params = {"network": LATENT_NET, "k": 20}


def _data(n_subjects=12, n_vertices=250):
    from fwk.plugins import get_registry

    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=n_vertices,
                                                            shapes=["neutral"]).load(None)
    tr = n_subjects - 3
    pre = Preprocessor().fit(np.asarray(col.positions[:tr, 0]))
    X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
    col.positions = X
    return FitData(col.template.with_vertices(pre.mean_neutral), col.select(np.arange(tr)),
                   col.select(np.arange(tr, n_subjects)))


@pytest.fixture(scope="module")
def data():
    return _data()


@pytest.fixture(scope="module")
def trained(tmp_path_factory, data):
    ctx = make_test_context(tmp_path_factory.mktemp("dsm"), epochs=1, batch_size=4)
    m = _dsm(network=NET, k=20, gamma=0.5)
    m.fit(data, ctx)
    return m


def _perfect(m, P, exact: bool = True):
    """Ground-truth features fed to the decoders, converted back and assembled (eq. 4.15).
    ``exact``: the euclidean features in float64 (``encode`` returns float32, whose round-off,
    ~6e-8 here, is not the property under test)."""
    if not exact:
        return m.decode_features(m.features(P))
    feats = [rep.scaler.transform(band) for rep, band in zip(m.reps, m.split(P))]
    assert all(f.dtype == np.float64 for f in feats)
    return m.decode_features(feats)


@pytest.mark.parametrize("scalings", [("std", "std"), ("none", "norm")])
def test_perfect_decoders_assemble_the_input_exactly(tmp_path, data, scalings):
    m = _dsm(network=NET, k=20, representations=[{"name": "euclidean", "scaling": s} for s in scalings])
    P = data.stack("train")
    m.template = data.template
    m._fit_assembler(data.template, P.mean(0), make_test_context(tmp_path).cache)
    m.reps = m._make_reps()
    for rep, band in zip(m.reps, m.split(P)):
        rep.fit(band, P.mean(0), data.template)
    V = data.stack("val")
    out = _perfect(m, V)
    assert np.abs(out - V).max() < 1e-8
    # and the bands really are different signals: neither alone is the input
    low, high = m.split(V)
    assert np.abs(low - V).max() > 1e-3 and np.abs(high - V).max() > 1e-3


def test_perfect_decoders_with_dr_high_band_no_ground_truth(trained, data):
    """The thesis default (dr norm on the high band) is not exactly invertible (dr integrates
    least-squares gradients); the assembly still lands close to the input without ever seeing it."""
    V = data.stack("val")
    out = _perfect(trained, V, exact=False)
    scale = np.abs(V).max()
    assert np.abs(out - V).max() < 0.05 * scale
    assert [r.name for r in trained.reps] == ["euclidean", "dr"]


@pytest.mark.parametrize("gamma", [0.0, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("mode", ["band", "element"])
def test_conditioning_mask_rate_in_training_never_at_inference(gamma, mode):
    from fwk_dsm import DSMNet

    torch.manual_seed(0)
    lat = [6, 5]
    net = DSMNet([torch.nn.Identity()] * 2, [torch.nn.Identity()] * 2, lat, gamma, mode)
    zs = [torch.ones(4000, 6), torch.ones(4000, 5) * 2]
    net.train()
    ins = net.decoder_inputs(zs)
    # decoder 0 sees its own code intact, band 1 zeroed at rate 1 - gamma (and vice versa)
    assert torch.equal(ins[0][:, :6], zs[0]) and torch.equal(ins[1][:, 6:], zs[1])
    other0, other1 = ins[0][:, 6:], ins[1][:, :6]
    for other, value in ((other0, 2.0), (other1, 1.0)):
        assert set(other.unique().tolist()) <= {0.0, value}  # no rescaling
        rate = float((other == 0).float().mean())
        assert abs(rate - (1 - gamma)) < 0.03
        if mode == "band" and 0 < gamma < 1:  # a whole band masked or not, per sample
            rows = (other == 0).all(1) | (other != 0).all(1)
            assert bool(rows.all())
    net.eval()
    for _ in range(3):
        ins = net.decoder_inputs(zs)
        assert torch.equal(ins[0], torch.cat(zs, 1)) and torch.equal(ins[1], torch.cat(zs, 1))


def test_each_optimiser_changes_only_its_own_band(trained, data):
    from fwk_dsm import band_losses
    from fwk_dsm.module import DSMModule
    from fwk.engine import TrainConfig

    net = trained.net
    module = DSMModule(net, [r.unscale for r in trained.reps], 1e-6, trained.band_names)
    module.train_config = TrainConfig(lr=1e-2)
    opts = [c["optimizer"] for c in module.configure_optimizers()]
    band_params = [list(net.encoders[b].parameters()) + list(net.decoders[b].parameters()) for b in range(2)]
    # the optimisers partition the parameters by band
    ids = [{id(p) for g in o.param_groups for p in g["params"]} for o in opts]
    assert ids[0] == {id(p) for p in band_params[0]} and ids[1] == {id(p) for p in band_params[1]}
    assert not ids[0] & ids[1]
    feats = [torch.as_tensor(f) for f in trained.features(data.stack("train"))]
    net.train()
    torch.manual_seed(1)
    losses, _ = band_losses(net, feats, [r.unscale for r in trained.reps], 1e-6)
    # L_b reaches no other band's parameters (detached conditioning)
    for b in range(2):
        grads = torch.autograd.grad(losses[b], band_params[1 - b], allow_unused=True, retain_graph=True)
        assert all(g is None or float(g.abs().max()) == 0.0 for g in grads)
    sum(losses).backward()
    for b in range(2):
        before = [[p.detach().clone() for p in ps] for ps in band_params]
        opts[b].step()
        changed = [any(not torch.equal(p, q) for p, q in zip(ps, bs)) for ps, bs in zip(band_params, before)]
        assert changed[b] and not changed[1 - b]
    net.eval()


def test_sample_is_deterministic_for_a_seed(trained):
    a, b, c = trained.sample(3, seed=5), trained.sample(3, seed=5), trained.sample(3, seed=6)
    assert a.shape == (3, trained.template.n_vertices, 3) and np.all(np.isfinite(a))
    assert np.array_equal(a, b) and not np.allclose(a, c)


def test_latent_slices_and_round_trip_of_state(trained, data, tmp_path):
    assert trained.slices == {"low": slice(0, 4), "high": slice(4, 8)}
    V = data.stack("val")
    z = trained.encode(V)
    assert z.shape == (len(V), 8)
    rec = trained.reconstruct(V)
    assert rec.shape == V.shape and np.all(np.isfinite(rec))
    save_state(tmp_path / "m.safetensors", trained.state_dict())
    m2 = _dsm(network=NET, k=20, gamma=0.5)
    m2.load_state_dict(load_state(tmp_path / "m.safetensors"), ctx=make_test_context(tmp_path))
    assert np.allclose(m2.reconstruct(V), rec, atol=1e-10)


def test_three_bands_train_and_assemble(tmp_path, data):
    ctx = make_test_context(tmp_path, epochs=1, batch_size=4)
    m = _dsm(network=NET, k=[10, 40])
    m.fit(data, ctx)
    assert m.band_names == ["band0", "band1", "high"] and m.latent_size == 12
    assert [r.name for r in m.reps] == ["euclidean", "euclidean", "dr"]
    V = data.stack("val")
    assert len(m.split(V)) == 3
    assert np.abs(m.assemble(m.split(V)) - V).max() < 1e-8
    out = m.reconstruct(V)
    assert out.shape == V.shape and np.all(np.isfinite(out))
    # perfect decoders with exact representations: the input again
    m.reps = [m.reps[0], m.reps[1], type(m.reps[0])(scaling="std")]
    m.reps[2].fit(m.split(data.stack("train"))[2], None, data.template)
    assert np.abs(_perfect(m, V) - V).max() < 1e-8


def test_k_above_n_is_clamped_with_a_message(tmp_path, data):
    msgs = []
    m = _dsm(network=NET)  # k = 500 > 250 vertices
    m._fit_assembler(data.template, data.template.vertices, make_test_context(tmp_path).cache, msgs.append)
    assert m.cuts == [data.template.n_vertices] and "clamped" in msgs[0]


def test_nested_components_are_recipe_parameters_with_defaults(tmp_path, data):
    """The assembler (built with dsm's k and mass) and the representations are specs like any
    other: the defaults are the thesis's, and a recipe can replace each of them."""
    m = _dsm(network=NET, k=20)
    assert m.assembler_spec.name == "spectral" and [s.name for s in m.rep_specs] == ["euclidean", "dr"]
    assert [s.params for s in m.rep_specs] == [{}, {}]  # euclidean's default scaling is std, dr's norm
    m = _dsm(network=NET, k=[10, 40], mass=False, low_representation={"name": "euclidean", "scaling": "none"},
             high_representation={"name": "euclidean", "scaling": "std"}, assembler={"eigen_k": 60})
    assert [(s.name, s.params) for s in m.rep_specs] == [("euclidean", {"scaling": "none"})] * 2 + [
        ("euclidean", {"scaling": "std"})]
    m._fit_assembler(data.template, data.template.vertices, make_test_context(tmp_path).cache)
    assert m.assembler.cuts == [10, 40] and not m.assembler.mass and m.assembler.eigen_k == 60
    with pytest.raises(RecipeError, match="network.*NetworkFactory"):
        _dsm(network={"name": "pca"}, k=20)._net_model(0)


def test_decoders_read_z_as_a_latent_map_without_a_dense_front_end(data):
    """Thesis 4.4.2-4.4.3, figure 4.1: Z is read as an (n_latent x sum of the bands' channels) map by
    each decoder's first transposed convolution; no Linear reads the whole Z, and an edit of one
    latent vertex of Z_high reaches D_low's first layer only inside that vertex's support."""
    m = _dsm(network=LATENT_NET, k=20)
    m.channels = [3, 9]
    torch.manual_seed(0)
    net = m._make_net(data.template)
    d = m.latent_size
    assert m.latents == [20, 20] and d == 40
    for dec in net.decoders:
        assert not any(isinstance(x, torch.nn.Linear) and x.in_features == d for x in dec.modules())
    net.eval()
    zs = [torch.randn(3, 20), torch.randn(3, 20)]
    seen = []
    first = net.decoders[0].convs[0]  # D_low's first layer
    hook = first.register_forward_pre_hook(lambda mod, args: seen.append(args[0].detach().clone()))
    with torch.no_grad():
        net.decode(zs)
    hook.remove()
    (x,) = seen
    assert x.shape == (3, 5, 8)  # (b, n_latent, c_low + c_high)
    assert torch.equal(x, torch.cat([zs[0].reshape(3, 5, 4), zs[1].reshape(3, 5, 4)], 2))
    nb = m._net_model(0).hierarchy.levels[-2].unpool
    with torch.no_grad():
        y = first(x)
        for v in range(5):
            x2 = x.clone()
            x2[:, v, 4:] += 1.0  # Z_high's channels at latent vertex v
            changed = (first(x2) - y).abs().amax(dim=(0, 2)) > 0
            support = torch.as_tensor([(nb.index[i][nb.mask[i] > 0] == v).any() for i in range(len(nb.index))])
            assert changed.any() and not (changed & ~support).any()


def test_latent_map_dsm_trains_and_reloads(tmp_path, data):
    ctx = make_test_context(tmp_path, epochs=1, batch_size=4)
    m = _dsm(network=LATENT_NET, k=20, gamma=0.5)
    m.fit(data, ctx)
    V = data.stack("val")
    rec = m.reconstruct(V)
    assert rec.shape == V.shape and np.all(np.isfinite(rec))
    m2 = _dsm(network=LATENT_NET, k=20, gamma=0.5)
    m2.load_state_dict(m.state_dict())
    assert np.allclose(m2.reconstruct(V), rec, atol=1e-8)
