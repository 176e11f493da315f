import pytest

from fwk.errors import RecipeError, UnknownComponentError
from fwk.plugins import registry_from
from fwk.recipes import apply_overrides, load_recipe, resolve

from . import fake_plugin


@pytest.fixture
def reg():
    return registry_from(fake_plugin)


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_valid_recipe_builds_nested_specs(tmp_path, reg):
    p = write(tmp_path, "r.yaml", "task: taskish\nmodel: {name: modelish, latent: 4, conv: {name: spiralish, length: 5}}\nopts: {alpha: 2}\n")
    r = resolve(load_recipe(p), reg)
    task = r.task.build()
    m = task.model.build()
    assert m.latent == 4 and m.conv.build().length == 5
    assert task.opts.alpha == 2.0 and task.opts.flag is False
    assert r.name == "r"


def test_unknown_nested_key_did_you_mean(tmp_path, reg):
    p = write(tmp_path, "r.yaml", "task: taskish\nmodel: {name: modelish, conv: {name: spiralish, lenght: 5}}\n")
    with pytest.raises(RecipeError, match=r"^model\.conv\.lenght: unknown parameter of spiralish; did you mean length\?"):
        resolve(load_recipe(p), reg)


def test_unknown_component_lists_choices(tmp_path, reg):
    p = write(tmp_path, "r.yaml", "task: taskish\nmodels: {a: {name: modelis}}\n")
    with pytest.raises(UnknownComponentError, match=r"models\.a\.name: unknown model 'modelis'; did you mean modelish\?.*registered: modelish"):
        resolve(load_recipe(p), reg)


@pytest.mark.parametrize("text,match", [
    ("task: taskish\ncount: two\n", r"^count: expected an integer"),
    ("task: taskish\nopts: {flag: 3}\n", r"^opts\.flag: expected true or false"),
    ("task: taskish\nmodel: {name: modelish, lr: fast}\n", r"^model\.lr: expected a number"),
    ("task: taskish\nbogus: 1\n", r"^bogus: unknown parameter of task taskish"),
    ("task: nope\n", r"^task: unknown task 'nope'"),
    ("task: taskish\ntrain: {epoch: 3}\n", r"^train\.epoch: unknown parameter.*did you mean epochs\?"),
])
def test_wrong_types_and_keys_name_the_path(tmp_path, reg, text, match):
    with pytest.raises(RecipeError, match=match):
        resolve(load_recipe(write(tmp_path, "r.yaml", text)), reg)


def test_extends_and_overrides(tmp_path, reg):
    write(tmp_path, "base.yaml", "task: taskish\ncount: 1\nmodel: {name: modelish, latent: 4}\n")
    sub = tmp_path / "sub"
    sub.mkdir()
    p = write(sub, "child.yaml", "extends: ../base.yaml\nmodel: {latent: 16}\n")
    data = load_recipe(p, ["count=5", "model.conv.length=3", "train.epochs=2"])
    r = resolve(data, reg)
    assert r.task.params["count"] == 5
    assert r.task.params["model"].params["latent"] == 16
    assert r.task.params["model"].params["conv"].params["length"] == 3
    assert r.train.epochs == 2


def test_extends_cycle(tmp_path, reg):
    write(tmp_path, "a.yaml", "extends: b.yaml\ntask: taskish\n")
    write(tmp_path, "b.yaml", "extends: a.yaml\n")
    with pytest.raises(RecipeError, match="cycle"):
        load_recipe(tmp_path / "a.yaml")


def test_safe_load_only(tmp_path, reg):
    p = write(tmp_path, "r.yaml", "task: !!python/object/apply:os.system ['echo hi']\n")
    with pytest.raises(RecipeError, match="not valid YAML"):
        load_recipe(p)


def test_no_dotted_import_paths(tmp_path, reg):
    p = write(tmp_path, "r.yaml", "task: taskish\nmodel: {name: os.path.join}\n")
    with pytest.raises(UnknownComponentError):
        resolve(load_recipe(p), reg)


def test_override_parsing():
    d = apply_overrides({"a": {"b": 1}, "ds": "x"}, ["a.b=2", "a.c=[1, 2]", "ds.n=3", "f=1e-3"])
    assert d["a"] == {"b": 2, "c": [1, 2]}
    assert d["ds"] == {"name": "x", "n": 3}
    with pytest.raises(RecipeError):
        apply_overrides({}, ["novalue"])
