"""What fwk checks of a plugin before it trains or loads data (issue 30, item 3): each with the
one-line message a plugin author reads."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from fwk.errors import PluginError
from fwk.protocols import CONV_BUILD_ARGS, Conv, plays
from fwk.recipes import Spec, make_spec
from fwk.testing.model import tiny_fit_data


# ----------------------------------------------------------------------------- conv output shapes

class Narrow(nn.Module):
    """A conv that returns one channel too few (a plugin author's slip)."""

    name = "narrow"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, short: int = 1):
        super().__init__()
        self.lin = nn.Linear(in_channels, out_channels - short)

    def reset_parameters(self) -> None:
        self.lin.reset_parameters()

    def forward(self, x):
        return self.lin(x)


class Raising(Narrow):
    """A conv whose forward fails."""

    name = "raising"

    def forward(self, x):
        raise ValueError("index 7 is out of bounds\nsecond line")


def _ae(conv_cls, **params):
    from fwk.plugins import get_registry

    reg = get_registry()
    model = reg.get("model", "ae")
    assert plays(conv_cls, Conv)
    conv = Spec("conv", conv_cls.name, {}, conv_cls, "models.ae.network.conv")
    sampler = make_spec("sampler", {"name": "simple", "levels": 2}, "models.ae.network.sampler", reg)
    return model(conv=conv, sampler=sampler, channels=[8, 16], latent=4, **params)


@pytest.fixture(scope="module")
def template():
    return tiny_fit_data(n_subjects=4).template


@pytest.mark.parametrize("layout", [{}, {"fully_convolutional": True}, {"latent_vertices": 2}])
def test_a_conv_of_the_wrong_width_stops_the_build_in_one_line(template, layout):
    m = _ae(Narrow, **layout)
    with pytest.raises(PluginError) as e:
        m.build_encoder(template, 3)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("models.ae.network.conv: conv 'narrow'")
    assert "at level " in msg and ("encoder" in msg or "strided" in msg), msg
    n0 = template.n_vertices
    if not layout:  # the first encoder conv: level 0, 3 -> 8 channels, 7 came back
        assert f"(1, {n0}, 3) to (1, {n0}, 7), expected (1, {n0}, 8)" in msg, msg


def test_the_decoder_output_conv_is_checked(template):
    m = _ae(Narrow)
    with pytest.raises(PluginError, match=r"conv 'narrow' .* at level \d, decoder block"):
        m.build_decoder(template, 3)


def test_a_conv_whose_forward_raises_is_named(template):
    with pytest.raises(PluginError) as e:
        _ae(Raising).build_encoder(template, 3)
    msg = str(e.value)
    assert "\n" not in msg and "conv 'raising'" in msg and "at level 0" in msg
    assert "raised ValueError: index 7 is out of bounds" in msg


def test_the_check_leaves_the_random_stream_alone(template):
    """Building checks each conv on zeros: the same seed gives the same weights and the same draws
    after the build, and the convs keep their train mode."""
    out = []
    for _ in range(2):
        torch.manual_seed(0)
        net = _ae_ok().build_encoder(template, 3)
        out.append(([p.detach().clone() for p in net.parameters()], torch.rand(3)))
        assert all(m.training for m in net.modules())
    (pa, ra), (pb, rb) = out
    assert torch.equal(ra, rb) and all(torch.equal(p, q) for p, q in zip(pa, pb))


def _ae_ok():
    from fwk.plugins import get_registry

    reg = get_registry()
    model = reg.get("model", "ae")
    conv = make_spec("conv", "spiral++", "models.ae.conv", reg)  # name-ok: a built-in conv to compare with
    sampler = make_spec("sampler", "quadric", "models.ae.sampler", reg)  # name-ok: its sampler
    return model(conv=conv, sampler=sampler, channels=[8, 16], latent=4)


# ----------------------------------------------------------------------------- what fwk list reports

def _module(name, **attrs):
    import types

    m = types.ModuleType(name)
    for k, v in attrs.items():
        setattr(m, k, v)
    return m


class PlyFolder:
    """A dataset of PLY files."""

    name = "ply-folder-test"

    def __init__(self, root: str = "."):
        self.root = root


def _fwk_list(monkeypatch, capsys, *plugins):
    import fwk.cli
    from fwk.plugins import registry_from

    reg = registry_from(*plugins)
    monkeypatch.setattr(fwk.cli, "get_registry", lambda: reg)
    assert fwk.cli.main(["list"]) == 0
    return reg, capsys.readouterr().err


def test_a_misspelled_hook_is_reported_by_fwk_list(monkeypatch, capsys):
    from fwk.hookspecs import hookimpl

    mine = _module("my_ply", fwk_register_dataset=hookimpl(lambda: [PlyFolder]))
    reg, err = _fwk_list(monkeypatch, capsys, mine)
    assert "broken plugin my_ply: hook fwk_register_dataset is not one of fwk's hooks; did you mean " \
           "fwk_register_datasets?" in err, err
    assert "ply-folder-test" not in reg.names("dataset")
    from fwk.errors import UnknownComponentError

    with pytest.raises(UnknownComponentError, match=r"plugins that failed to load \(fwk list\): my_ply"):
        reg.get("dataset", "ply-folder-test")


def test_an_unmarked_hook_is_reported(monkeypatch, capsys):
    mine = _module("my_unmarked", fwk_register_datasets=lambda: [PlyFolder])
    _, err = _fwk_list(monkeypatch, capsys, mine)
    assert "broken plugin my_unmarked: fwk_register_datasets is not marked @hookimpl" in err, err


def test_a_plugin_that_registers_nothing_is_reported(monkeypatch, capsys):
    from fwk.hookspecs import hookimpl

    empty = _module("my_empty", fwk_register_metrics=hookimpl(lambda: []))
    nothing = _module("my_nothing")
    _, err = _fwk_list(monkeypatch, capsys, empty, nothing)
    assert "broken plugin my_empty: registers no component: none of its hooks" in err, err
    assert "broken plugin my_nothing: registers no component" in err, err


def test_an_installed_distribution_registering_nothing_names_it(monkeypatch):
    """Through the entry points (the distribution's name and version in the report)."""
    from importlib.metadata import EntryPoint

    import fwk.plugins

    class Dist:
        name, version = "my-ply", "0.3"

    ep = EntryPoint("my-ply", "tests.core.test_plugin_checks:_EMPTY", "fwk")
    ep = ep._for(Dist())  # as importlib.metadata gives it: with its distribution
    monkeypatch.setattr(fwk.plugins, "entry_points", lambda group: [ep])
    pm = fwk.plugins.make_plugin_manager(load_entrypoints=True)
    from fwk.registry import build_registry

    reg = build_registry(pm)
    (b,) = [b for b in reg.broken if b.plugin == "my-ply"]
    assert "registers no component" in b.error
    assert "(distribution my-ply 0.3)" in b.error, b.error


_EMPTY = _module("empty_entry_point")


# ----------------------------------------------------------------------------- unannotated parameters

def test_an_unannotated_constructor_parameter_is_refused_at_registration():
    from fwk.hookspecs import hookimpl
    from fwk.plugins import registry_from

    class Loose:
        """A metric with an unannotated parameter."""

        name = "loose-test"

        def __init__(self, workers=1, scale: float = 1.0):
            self.workers = workers

    class Fine(PlyFolder):
        """Another component of the same plugin, registered."""

        name = "fine-test"

    mine = _module("my_loose", fwk_register_metrics=hookimpl(lambda: [Loose]),
                   fwk_register_datasets=hookimpl(lambda: [Fine]))
    reg = registry_from(mine)
    assert "loose-test" not in reg.names("metric") and "fine-test" in reg.names("dataset")
    (b,) = reg.broken
    assert b.plugin == "my_loose"
    assert b.error.startswith("metric 'loose-test' not registered: constructor parameter workers has no annotation"), b


# ----------------------------------------------------------------------------- roles and constructor errors in a run

class PickyConv(Narrow):
    """A conv whose constructor refuses a parameter (as a plugin should: a RecipeError naming it)."""

    name = "picky-test"

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, k: int = 0):
        from fwk.errors import RecipeError

        if k < 1:
            raise RecipeError(f"k: at least 1, got {k}")
        super().__init__(in_channels, out_channels, hierarchy, level, short=0)


class HalfModel:
    """A reconstruction model that forgot load_state_dict (and reconstruct)."""

    name = "half-test"
    task_family = "reconstruct"

    def __init__(self, latent: int = 4):
        self.latent = latent

    def fit(self, data, ctx) -> None:
        raise AssertionError("never reached")

    def state_dict(self) -> dict:
        return {}


@pytest.fixture
def run_env(tmp_path, monkeypatch):
    """A registry with the built-ins and this module's test plugin; the cache and runs in tmp."""
    from fwk.hookspecs import hookimpl
    from fwk.plugins import registry_from

    mine = _module("my_checks_plugin", fwk_register_convs=hookimpl(lambda: [PickyConv]),
                   fwk_register_models=hookimpl(lambda: [HalfModel]))
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("FWK_THREADS", "1")
    reg = registry_from(mine, load_entrypoints=True)
    assert not reg.broken, reg.broken
    return reg


def _recipe(tmp_path, models: str, task: str = "reconstruct") -> str:
    p = tmp_path / "r.yaml"
    p.write_text(f"task: {task}\nseed: 0\ndataset: {{name: synthetic-heads, n_vertices: 300, n_subjects: 12}}\n"
                 f"train: {{epochs: 1, batch_size: 8}}\nmodels: {models}\nrenders: 0\n")
    return str(p)


def _no_data(monkeypatch, reg):
    """Make any dataset load fail the test: the check must come first."""
    cls = reg.get("dataset", "synthetic-heads")
    monkeypatch.setattr(cls, "load", lambda self, cache=None: pytest.fail("the dataset was loaded"))


def test_a_model_missing_role_members_is_refused_before_data_loads(tmp_path, monkeypatch, run_env):
    from fwk.errors import RecipeError
    from fwk.runs import execute

    _no_data(monkeypatch, run_env)
    with pytest.raises(RecipeError) as e:
        execute(_recipe(tmp_path, "{half: {name: half-test}}"), runs_dir=str(tmp_path / "runs"), quiet=True,
                registry=run_env)
    msg = str(e.value)
    assert msg.startswith("models.half: model 'half-test' (tests.core.test_plugin_checks.HalfModel, a reconstruct "
                          "model) does not play the Model role: it lacks load_state_dict ("), msg
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_a_task_asks_for_its_family_role_before_data_loads(tmp_path, monkeypatch, run_env):
    """The blendshapes task's models play BlendshapeModel (``Kind("model", BlendshapeModel)``): a
    reconstruction model there is refused while the recipe is validated, naming what it lacks."""
    from fwk.errors import RecipeError
    from fwk.runs import execute

    _no_data(monkeypatch, run_env)
    with pytest.raises(RecipeError, match=r"^models\.p: model 'pca' \(.*, a reconstruct model\) does not play the "
                                          r"BlendshapeModel role: it lacks expressions, predict, predict_all"):
        execute(_recipe(tmp_path, "{p: {name: pca}}", task="blendshapes"),  # name-ok: a model of the other family
                runs_dir=str(tmp_path / "runs"), quiet=True, registry=run_env)


@pytest.mark.parametrize("model", ["{d: {name: dsm, k: 20, network: {name: pca}}}",
                                   "{d: {name: pbs, network: {name: pca}}}"])
def test_a_network_that_lends_no_networks_is_refused_before_data_loads(tmp_path, monkeypatch, run_env, model):
    """dsm, pb and pbs take ``network:`` as ``Kind("model", NetworkFactory)``: a model that does
    not lend an encoder and a decoder is refused while the recipe is validated, naming what it
    lacks (it used to fail when that model was fitted, after others had trained)."""
    from fwk.errors import RecipeError
    from fwk.runs import execute

    _no_data(monkeypatch, run_env)
    task = "blendshapes" if "pbs" in model else "reconstruct"
    with pytest.raises(RecipeError, match=r"^models\.d\.network: model 'pca' \(.*\) does not play the "
                                          r"NetworkFactory role: it lacks variational, build_encoder, build_decoder"):
        execute(_recipe(tmp_path, model, task=task), runs_dir=str(tmp_path / "runs"), quiet=True, registry=run_env)


def test_a_plugin_constructor_error_names_the_full_path_and_what_is_left(tmp_path, run_env):
    """The conv is built when its network is (after the data loaded): its RecipeError names
    ``models.<label>.conv.k`` and says that no run directory is left."""
    from fwk.errors import RecipeError
    from fwk.runs import execute

    runs = tmp_path / "runs"
    with pytest.raises(RecipeError) as e:
        execute(_recipe(tmp_path, "{ae: {name: ae, channels: [8], latent: 4, conv: {name: picky-test}, "
                                  "sampler: {name: simple, levels: 1}}}"), runs_dir=str(runs), quiet=True,
                registry=run_env)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("models.ae.conv.k: at least 1, got 0"), msg
    assert "no run directory is left" in msg, msg
    assert list(runs.iterdir()) == []


def test_a_borrowed_networks_conv_error_names_network_conv(tmp_path, run_env):
    """dsm borrows its networks (``network:``): the conv's error reads ``models.d.network.conv.k``."""
    from fwk.errors import RecipeError
    from fwk.runs import execute

    with pytest.raises(RecipeError) as e:
        execute(_recipe(tmp_path, "{d: {name: dsm, k: 20, network: {name: vae, channels: [8], latent: 4, "
                                  "conv: {name: picky-test}, sampler: {name: simple, levels: 1}}}}"),
                runs_dir=str(tmp_path / "runs"), quiet=True, registry=run_env)
    assert str(e.value).startswith("models.d.network.conv.k: at least 1, got 0"), str(e.value)


def test_with_key_path():
    from fwk.recipes import with_key_path

    assert with_key_path("k: at least 1", "models.ae.network.conv") == "models.ae.network.conv.k: at least 1"
    assert with_key_path("needs triangles", "models.ae.conv") == "models.ae.conv: needs triangles"
    assert with_key_path("models.ae.conv.k: x", "models.ae") == "models.ae.conv.k: x"
    assert with_key_path("models.ae.x: y", "models.ae.conv") == "models.ae.x: y"


def test_a_task_without_run_is_refused_when_validating():
    from fwk.errors import RecipeError
    from fwk.hookspecs import hookimpl
    from fwk.plugins import registry_from
    from fwk.recipes import resolve

    class Idle:
        """A task that forgot run."""

        name = "idle-test"

        def __init__(self, n: int = 1):
            self.n = n

    reg = registry_from(_module("my_idle", fwk_register_tasks=hookimpl(lambda: [Idle])))
    with pytest.raises(RecipeError, match=r"^task: task 'idle-test' \(.*Idle\) does not play the Task role: "
                                          r"it lacks run \("):
        resolve({"task": "idle-test"}, reg)
