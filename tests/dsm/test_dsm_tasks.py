"""End to end: edit + interpolate trained inline, the same studies from the finished run, and
``fwk sample`` writing OBJs with the dataset's polygons."""
import argparse
import json
from pathlib import Path

import numpy as np
import pytest

NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
SMOKE = Path(__file__).resolve().parents[2] / "recipes" / "smoke" / "dsm.yaml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from fwk.plugins import get_registry
    from fwk.runs import execute

    out = tmp_path_factory.mktemp("runs")
    over = ["dataset.n_vertices=250", "dataset.n_subjects=12", "train.epochs=1", "metrics=[l1, dame]",
            "renders=0", f"models.dsm.network={json.dumps(NET)}", f"models.dsm-g04.network={json.dumps(NET)}",
            "models.dsm.k=20", "models.dsm-g04.k=20",
            f"models.vae-euclidean-std={json.dumps({**NET, 'latent': 8})}", "max_subjects=2"]
    return execute(str(SMOKE), over, runs_dir=str(out), quiet=True, registry=get_registry())


def test_inline_run_writes_pictures_meshes_and_disentanglement(run):
    m = json.loads((run / "metrics.json").read_text())
    d = m["disentanglement"]
    for label in ("dsm", "dsm-g04"):
        for band in ("low", "high"):
            shares = d["dsm"][label][band]["shares"]
            assert abs(sum(shares.values()) - 1) < 1e-6 and 0 <= d["dsm"][label][band]["own_share"] <= 1
            r = d["dsm"][label][band]  # the like-with-like measures beside it
            assert abs(sum(r["normalised_shares"].values()) - 1) < 1e-6 and min(r["variance_units"].values()) >= 0
        assert set(d["dsm"][label]["cross_response"]) == {"low<-high", "high<-low"}
        assert all(v >= 0 for v in d["dsm"][label]["cross_response"].values())
    c = d["compare"]["vae-euclidean-std"]
    assert abs(sum(c["shares"].values()) - 1) < 1e-6 and abs(sum(c["normalised_shares"].values()) - 1) < 1e-6
    report = (run / "report.md").read_text()
    assert "training variance" in report and "rho low <- high" in report
    for f in ("edit_low.png", "edit_high.png", "interpolation_dsm.png", "interpolation_dsm-g04.png"):
        assert (run / "figures" / f).stat().st_size > 1000
    objs = sorted((run / "interpolation" / "dsm").glob("*.obj"))
    assert len(objs) == 9
    assert (run / "reconstruct" / "models" / "dsm.safetensors").exists()
    assert "dsm" in m["models"] and "test" in m["models"]["dsm"]


def test_interpolation_ends_and_vertex_space(run):
    """alpha = beta = 0 decodes subject 1's code; the vertex-space ends are the subjects themselves."""
    from fwk.data.io import read_obj
    from fwk_dsm_tasks import load_models

    env = load_models(run / "reconstruct")
    P = env.splits["test"]
    V0, t = read_obj(run / "interpolation" / "vertex" / "delta0.obj")
    assert np.abs(V0 - env.to_input_units(P[:1])[0]).max() < 1e-5
    m = env.models["dsm"]
    want = env.to_input_units(m.decode(m.encode(P[:1])))[0]
    V, _ = read_obj(run / "interpolation" / "dsm" / "alpha0_beta0.obj")
    assert np.abs(V - want).max() < 1e-5
    assert t.n_polygons == env.template.n_polygons


def test_studies_from_a_finished_run(run, tmp_path):
    from fwk.plugins import get_registry
    from fwk.runs import execute

    recipe = tmp_path / "interp.yaml"
    recipe.write_text(f"task: interpolate\nrun: {run / 'reconstruct'}\nalphas: [0, 1]\nbetas: [0, 1]\n"
                      "write_obj: false\nedit: {directions: [0], amounts: [1], max_subjects: 1}\n")
    out = execute(str(recipe), runs_dir=str(tmp_path / "r"), quiet=True, registry=get_registry())
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["interpolation"]["models"]) == {"dsm", "dsm-g04"} and "disentanglement" in m
    assert not (out / "reconstruct").exists()


def test_both_run_and_models_is_a_recipe_error(tmp_path):
    from fwk.errors import RecipeError
    from fwk_dsm_tasks import Edit

    with pytest.raises(RecipeError, match="not both"):
        Edit(run="x", models={"a": "pca"})


def test_chained_settings_are_validated_by_the_recipe(tmp_path):
    """`interpolate: {...}` in an edit recipe holds interpolation settings only (not models)."""
    from fwk.errors import RecipeError
    from fwk.plugins import get_registry
    from fwk.recipes import resolve

    base = {"task": "edit", "run": str(tmp_path), "interpolate": {"alphas": [0, 1]}}
    task = resolve(base, get_registry()).task.build()
    assert task.interpolate.alphas == [0.0, 1.0] and task.interpolate.subjects == [0, 1]
    for bad, match in (({"run": "x"}, "interpolate.run: unknown parameter"),
                       ({"subjects": [0]}, "subjects: give two")):
        with pytest.raises(RecipeError, match=match):
            resolve({**base, "interpolate": bad}, get_registry())


def test_sample_writes_deterministic_objs(run, tmp_path):
    from fwk.data.io import read_obj
    from fwk.generate import run_sample

    a = argparse.Namespace(run_dir=str(run), n=2, out=str(tmp_path / "a"), seed=3, model=None, quiet=True)
    assert run_sample(a) == 0
    a.out = str(tmp_path / "b")
    run_sample(a)
    A, tA = read_obj(tmp_path / "a" / "sample_001.obj")
    B, _ = read_obj(tmp_path / "b" / "sample_001.obj")
    assert A.shape == (250, 3) or A.shape[0] == tA.n_vertices
    assert np.array_equal(A, B) and np.all(np.isfinite(A))


def test_sample_chooses_the_model_by_role(run):
    """Without --model, the first band model (dsm) samples; --model picks any generative model."""
    from fwk.errors import FwkError
    from fwk.generate import sample_meshes

    label, P, t = sample_meshes(run, 1, seed=0)
    assert label == "dsm" and P.shape == (1, t.n_vertices, 3)
    label, P, _ = sample_meshes(run, 2, seed=0, model="vae-euclidean-std")
    assert label == "vae-euclidean-std" and P.shape[0] == 2 and np.all(np.isfinite(P))
    with pytest.raises(FwkError, match="not a model"):
        sample_meshes(run, 1, model="nope")
