"""The dataset-stats task passes fwk's task contract suite, its figures equal a naive loop over
the meshes of each split, and `fwk run` runs it from a recipe."""
import json

import numpy as np
import pytest

from fwk.data import MeshCollection
from fwk.data.split import SplitConfig, split_subjects
from fwk.errors import DataError
from fwk.plugins import get_registry
from fwk.runs import make_test_context
from fwk.testing.task import TaskContract
from fwk_example_plugin.stats import DatasetStats, summarise
from recipe_runs import run_recipe

SMALL = {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12}


class TestDatasetStatsContract(TaskContract):
    component = DatasetStats
    params = {"dataset": SMALL}


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("task", "dataset-stats")
    assert e.component is DatasetStats and e.plugin == "example-stats"


def _naive(col, subjects, neutral="neutral"):
    """The figures of one split, one mesh and one vertex at a time."""
    index = {s: i for i, s in enumerate(col.subjects)}
    j0 = col.shape_names.index(neutral)
    lo, hi = [np.inf] * 3, [-np.inf] * 3
    meshes, ext = 0, []
    disp = {s: [] for s in col.shape_names if s != neutral}
    for s in subjects:
        i = index[s]
        for j, shape in enumerate(col.shape_names):
            if not col.present[i, j]:
                continue
            P = np.asarray(col.positions[i, j])
            meshes += 1
            for a in range(3):
                lo[a], hi[a] = min(lo[a], *P[:, a]), max(hi[a], *P[:, a])
            if j == j0:
                ext.append([P[:, a].max() - P[:, a].min() for a in range(3)])
            elif col.present[i, j0]:
                N = np.asarray(col.positions[i, j0])
                disp[shape].append([float(np.sqrt(sum((P[v, a] - N[v, a]) ** 2 for a in range(3))))
                                    for v in range(len(P))])
    return {"meshes": meshes, "extent": [h - l for h, l in zip(hi, lo)], "neutral_extent_mean": np.mean(ext, 0),
            "displacement": {s: (len(d), float(np.mean(d)), float(np.max(d))) for s, d in disp.items()}}


def _run(tmp_path, **params):
    ctx = make_test_context(tmp_path)
    DatasetStats(**params).run(ctx)
    return ctx, json.loads((ctx.run_dir / "metrics.json").read_text()), get_registry()


def test_figures_equal_a_naive_loop_over_the_meshes(tmp_path):
    ctx, m, reg = _run(tmp_path, dataset=SMALL, split=SplitConfig([0.6, 0.2, 0.2]))
    col = reg.get("dataset", "synthetic-heads")(n_vertices=300, n_subjects=12).load(ctx.cache)
    split = json.loads((ctx.run_dir / "split.json").read_text())
    # the split is the built-in tasks' (fwk.data.split_subjects with the recipe's seed and ratios)
    assert split == split_subjects(col.subjects, SplitConfig([0.6, 0.2, 0.2]), ctx.seed)
    assert m["dataset"]["units"] == "cm" and m["dataset"]["n_vertices"] == col.template.n_vertices
    assert m["dataset"]["scale"] > 0 and (ctx.run_dir / "stats" / "preprocess.npz").exists()
    for name in ("train", "val", "test"):
        got, ref = m["splits"][name], _naive(col, split[name])
        assert got["subjects"] == len(split[name]) and got["meshes"] == ref["meshes"] == 4 * len(split[name])
        assert got["n_vertices"] == col.template.n_vertices and got["n_faces"] == col.template.n_polygons
        assert got["n_triangles"] == len(col.template.triangles)
        assert np.allclose(got["extent"], ref["extent"], rtol=1e-12)
        assert np.allclose(got["neutral_extent_mean"], ref["neutral_extent_mean"], rtol=1e-12)
        assert set(got["displacement"]) == set(ref["displacement"]) == {
            "face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"}
        for shape, (count, mean, mx) in ref["displacement"].items():
            d = got["displacement"][shape]
            assert d["subjects"] == count and np.isclose(d["mean"], mean, rtol=1e-10) and np.isclose(d["max"], mx)
            assert 0 < d["mean"] < d["max"] < 10  # cm: an expression moves a head by millimetres to centimetres
    report = (ctx.run_dir / "report.md").read_text()
    assert "| split | subjects | meshes |" in report and "## Displacement from the neutral" in report
    assert f"{m['splits']['test']['displacement']['mouth-wide']['max']:.4g}" in report
    assert "train:" in (ctx.run_dir / "log.txt").read_text()


def test_missing_shapes_and_a_chosen_subset(tmp_path):
    """A subject without a shape counts for that shape's displacement neither as a mesh nor as a subject."""
    reg = get_registry()
    ds = reg.get("dataset", "synthetic-heads")(n_vertices=300, n_subjects=6, shapes=["neutral", "mouth-wide"])
    col = ds.load(None)
    present = col.present.copy()
    present[:3, 1] = False  # three subjects lack mouth-wide
    holey = MeshCollection(col.template, col.subjects, col.shape_names, np.array(col.positions), present, col.name)
    s = summarise(holey, np.arange(6), ["neutral", "mouth-wide"], "neutral")
    ref = _naive(holey, holey.subjects)
    assert s["meshes"] == ref["meshes"] == 9 and s["displacement"]["mouth-wide"]["subjects"] == 3
    assert np.isclose(s["displacement"]["mouth-wide"]["mean"], ref["displacement"]["mouth-wide"][1])
    none = summarise(holey, np.arange(3), ["neutral", "mouth-wide"], "neutral")
    assert none["displacement"]["mouth-wide"] == {"subjects": 0, "mean": None, "max": None}
    empty = summarise(holey, np.arange(0), ["neutral", "mouth-wide"], "neutral")
    assert empty["subjects"] == 0 and empty["extent"] is None and empty["neutral_extent_mean"] is None
    # shapes: a subset (the neutral always among them); an unknown shape names the dataset's shapes
    _, m, _ = _run(tmp_path / "a", dataset=SMALL, shapes=["mouth-wide"])
    assert m["dataset"]["shapes"] == ["neutral", "mouth-wide"]
    assert list(m["splits"]["train"]["displacement"]) == ["mouth-wide"]
    with pytest.raises(DataError, match="no shape 'smile'"):
        _run(tmp_path / "b", dataset=SMALL, shapes=["smile"])


RECIPE = """
task: dataset-stats
name: heads-stats
seed: 3
dataset: {name: synthetic-heads, n_vertices: 300, n_subjects: 10, shapes: [neutral, mouth-wide]}
split: {ratios: [0.8, 0.1, 0.1]}
"""


def test_fwk_run_of_a_dataset_stats_recipe(tmp_path):
    run_dir = run_recipe(tmp_path, "stats.yaml", RECIPE)
    assert run_dir.name.startswith("heads-stats")
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["dataset"]["subjects"] == {"train": 8, "val": 1, "test": 1}
    assert m["dataset"]["shapes"] == ["neutral", "mouth-wide"]
    assert json.loads((run_dir / "split.json").read_text()) == split_subjects(
        [f"s{i:04d}" for i in range(10)], SplitConfig([0.8, 0.1, 0.1]), 3)
    for f in ("report.md", "recipe.yaml", "versions.json", "log.txt"):
        assert (run_dir / f).exists(), f
    assert not (run_dir / "RUNNING").exists() and not (run_dir / "FAILED").exists()
