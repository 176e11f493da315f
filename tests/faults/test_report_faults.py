"""`fwk report` never puts numbers that do not compare into one table silently, and its texts and
plots say their units (issue 16, reproduction 9, the report parts)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from fwk.cli import main
from fwk.evaluation.cli_report import _Dir
from fwk.evaluation.report import dataset_line, reconstruction_figures, scatter_figure, write_report


def _run(folder, task, dataset, l1, dame, scale=0.1, units="cm"):
    folder.mkdir(parents=True)
    (folder / "recipe.yaml").write_text(yaml.safe_dump({"task": task, "dataset": dataset, "split": {"ratios": [0.8, 0.1, 0.1]}},
                                                  sort_keys=False))
    res = {"models": {"m": {"test": {"l1": {"mean": l1, "units": "input", "mean_input": l1 / scale, "units_input": units},
                                     "dame": {"mean": dame, "units": "rad", "mean_input": dame, "units_input": "rad"}}}},
           "dataset": {"name": dataset if isinstance(dataset, str) else dataset["name"], "n_vertices": 500, "units": units,
                       "subjects": {"train": 17, "val": 2, "test": 5}}}
    write_report(_Dir(folder), folder.name, res)
    return folder


def test_runs_of_different_tasks_or_datasets_are_refused_unless_mixed(tmp_path, capsys):
    a = _run(tmp_path / "a", "blendshapes", {"name": "synthetic-heads", "n_vertices": 500}, 0.004, 0.02)
    b = _run(tmp_path / "b", "reconstruct", {"name": "synthetic-heads", "n_vertices": 500}, 0.003, 0.03)
    c = _run(tmp_path / "c", "reconstruct", {"name": "synthetic-heads", "n_vertices": 600}, 0.002, 0.04)
    d = _run(tmp_path / "d", "reconstruct", {"name": "synthetic-heads", "n_vertices": 600}, 0.001, 0.05)
    out = tmp_path / "out"
    for pair, what in (((a, b), "task: a blendshapes; b reconstruct"), ((b, c), "dataset: b {n_vertices: 500}; c {n_vertices: 600}")):
        capsys.readouterr()
        assert main(["report", *map(str, pair), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and what in err and "--mix" in err, err
        assert not out.exists()
    before = (a / "metrics.json").read_bytes()
    assert main(["report", str(a), str(b), "--out", str(a), "--mix"]) == 2  # into a run: its numbers would go
    assert "a run directory" in capsys.readouterr().err and (a / "metrics.json").read_bytes() == before
    assert main(["report", str(a), str(b), "--out", str(out), "--mix"]) == 0
    text = (out / "report.md").read_text()
    assert "mixed with --mix: the runs differ in task: a blendshapes; b reconstruct" in text
    assert main(["report", str(c), str(d), "--out", str(tmp_path / "same")]) == 0  # like with like: no word
    assert "--mix" not in (tmp_path / "same" / "report.md").read_text()
    # the same data written two ways (a name; a mapping with a default spelled out) compares equal
    e = _run(tmp_path / "e", "reconstruct", {"name": "synthetic-heads", "n_vertices": 6000, "seed": 0}, 0.1, 0.2)
    f = _run(tmp_path / "f", "reconstruct", "synthetic-heads", 0.2, 0.1)
    assert main(["report", str(e), str(f), "--out", str(tmp_path / "ef")]) == 0


def test_dataset_line_in_words(tmp_path):
    line = dataset_line({"name": "synthetic-heads", "n_vertices": 605, "units": "cm", "scale": 0.0412345678,
                         "subjects": {"train": 34, "val": 2, "test": 4}})
    assert line == "name synthetic-heads, n_vertices 605, units cm, scale 0.0412346, subjects 34 train / 2 val / 4 test"
    _run(tmp_path / "a", "reconstruct", {"name": "x"}, 0.1, 0.2)
    text = (tmp_path / "a" / "report.md").read_text()
    assert "{" not in text.split("Dataset: ")[1].splitlines()[0]


def test_scatter_axes_say_their_units(tmp_path, monkeypatch):
    import fwk.evaluation.report as rep

    seen = {}

    def capture(pts, path, xlabel, ylabel, **kw):
        seen.update(pts=pts, x=xlabel, y=ylabel)
        return path

    monkeypatch.setattr(rep, "scatter_pareto", capture)
    res = {"models": {"a": {"test": {"l1": {"mean": 0.01, "units": "input", "mean_input": 0.1, "units_input": "cm"},
                                     "fmpd": {"mean": 0.5, "units": "1", "mean_input": 0.5, "units_input": "1"}}},
                      "b": {"test": {"l1": {"mean": 0.02, "units": "input", "mean_input": 0.2, "units_input": "cm"},
                                     "fmpd": {"mean": 0.4, "units": "1", "mean_input": 0.4, "units_input": "1"}}}}}
    scatter_figure(_Dir(tmp_path), res, "test", "l1", "fmpd")
    assert seen["x"] == "L1 (test, cm)" and seen["y"] == "FMPD (test, unitless)"
    assert seen["pts"] == {"a": (0.1, 0.5), "b": (0.2, 0.4)}  # plotted in the dataset's units
    del res["models"]["b"]["test"]["l1"]["mean_input"]  # not every model has them: evaluation space
    scatter_figure(_Dir(tmp_path), res, "test", "l1", "fmpd")
    assert seen["x"] == "L1 (test, evaluation space)" and seen["pts"]["a"] == (0.01, 0.5)


def test_colour_bars_say_their_units(tmp_path, monkeypatch):
    import fwk.evaluation.report as rep
    from fwk.plugins import get_registry
    from fwk.testing.model import tiny_fit_data

    data = tiny_fit_data(n_subjects=5, n_vertices=200)
    P = data.stack("train")[:2]
    rows_of = {}

    def capture(rows, template, path, view="front"):
        rows_of[str(path)] = rows
        return path

    monkeypatch.setattr(rep, "render_grid", capture)
    metrics = [get_registry().get("metric", n)() for n in ("l1", "dame")]
    tpl = data.template
    tpl.units = "cm"
    reconstruction_figures(_Dir(tmp_path), tpl, {"test": P}, {"m": {"test": P + 0.01}}, metrics, n_rows=1, scale=0.5)
    bars = {c["bar"] for rows in rows_of.values() for row in rows for c in row if "bar" in c}
    assert bars == {"L1 (cm)", "DAME (rad)"}
    cell = next(c for rows in rows_of.values() for row in rows for c in row if c.get("bar") == "L1 (cm)")
    assert np.allclose(cell["scalars"], 0.01 / 0.5)  # in cm: the evaluation space's 0.01 over the scale
    rows_of.clear()
    reconstruction_figures(_Dir(tmp_path), tpl, {"test": P}, {"m": {"test": P + 0.01}}, metrics, n_rows=1)
    assert {c["bar"] for rows in rows_of.values() for row in rows for c in row if "bar" in c} == \
        {"L1 (evaluation space)", "DAME (rad)"}


def test_point_labels_do_not_overprint(tmp_path):
    """Thirty k values within a hair of each other (a PBS k sweep): the placed labels' boxes are
    disjoint and the front's points are labelled first."""
    from fwk.evaluation.plots import _plt, place_labels

    plt = _plt()
    fig, ax = plt.subplots()
    P = np.array([[1 + 0.001 * k, 2 - 0.001 * k] for k in range(30)] + [[3.0, 3.0]])
    ax.scatter(P[:, 0], P[:, 1])
    labels = [f"k={k}" for k in range(30)] + ["far"]
    texts = place_labels(ax, P, labels, first=[29, 0])
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in texts]
    assert all(not boxes[i].overlaps(boxes[j]) for i in range(len(boxes)) for j in range(i))
    shown = [t.get_text() for t in texts]
    assert shown[:2] == ["k=29", "k=0"] and "far" in shown and len(shown) < len(labels)
    plt.close(fig)


def test_metrics_json_of_a_combined_report_names_its_runs(tmp_path):
    a = _run(tmp_path / "a", "reconstruct", {"name": "x"}, 0.1, 0.2)
    b = _run(tmp_path / "b", "reconstruct", {"name": "x"}, 0.2, 0.1)
    assert main(["report", str(a), str(b), "--out", str(tmp_path / "o")]) == 0
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert set(m["models"]) == {"a:m", "b:m"} and set(m["runs"]) == {"a", "b"}
