"""Renders (pyvista and the matplotlib fallback), Pareto fronts, tables and reports."""
import itertools
import json

import numpy as np
import pytest

from fwk.data import Template
from fwk.evaluation import evaluate, evaluate_summary, markdown_table, pareto_front, summarise, write_report
from fwk.evaluation.cli_report import _Dir


def sphere(sub=3):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub)
    V = np.asarray(m.vertices) * [0.8, 1.0, 0.9]
    return V, Template(V, np.asarray(m.faces), units="cm")


def _png(path):
    import matplotlib.image as mpimg

    return mpimg.imread(str(path))[..., :3]


@pytest.mark.parametrize("backend", ["pyvista", "matplotlib"])
def test_render_mesh_shaded_and_coloured(tmp_path, monkeypatch, backend):
    from fwk.evaluation.render import render_grid, render_mesh

    monkeypatch.setenv("FWK_RENDER_BACKEND", backend)
    V, t = sphere()
    plain = render_mesh(V, t, tmp_path / "plain.png", view="front", size=(200, 220))
    img = _png(plain)
    assert img.shape[:2] == (220, 200)
    fg = np.any(img < 0.97, axis=-1)  # not the white background
    assert 0.15 < fg.mean() < 0.9  # the sphere fills a good part of the frame, not all of it
    grey = img[fg].mean(-1)
    assert grey.std() > 0.03  # shaded, not a flat silhouette
    # a map that is 0 on one half and 1 on the other: two distinct colours on the mesh
    s = (V[:, 0] > 0).astype(float)
    cm = render_mesh(V, t, tmp_path / "map.png", view="three-quarter", scalars=s, cmap="viridis",
                     colorbar_title="err", size=(200, 220))
    img2 = _png(cm)
    fg2 = np.any(img2 < 0.97, axis=-1)
    hue = img2[fg2][:, 1] - img2[fg2][:, 2]  # viridis: low end blue-purple, high end yellow-green
    assert hue.max() - hue.min() > 0.3
    grid = render_grid([[(V, None, "gt"), (V, s, "m1"), (V * 1.01, s, "m2")]], t, tmp_path / "grid.png",
                       view=["front", "three-quarter"], cell_size=(120, 140))
    h, w = _png(grid).shape[:2]
    assert w == 360 and h > 140  # the meshes' cells, the titles' band above and the colour bar's below


def test_render_grid_shares_colour_limits():
    from fwk.evaluation.render import _bars, _cells, _shared_clims

    V, _ = sphere(1)
    cells = _cells([[(V, None, "gt"), {"V": V, "scalars": np.linspace(0, 1, len(V)), "bar": "L1"},
                     {"V": V, "scalars": np.linspace(0, 3, len(V)), "bar": "L1"},
                     {"V": V, "scalars": np.linspace(0, 5, len(V)), "bar": "DAME", "clim": (0, 9)}]])
    _shared_clims(cells)
    _bars(cells)
    row = cells[0]
    assert row[1]["clim"] == row[2]["clim"]
    assert np.isclose(row[1]["clim"][1], np.median([np.percentile(np.linspace(0, m, len(V)), 99) for m in (1, 3)]))
    assert row[3]["clim"] == (0, 9)
    assert [c.get("show_bar") for c in row] == [None, False, True, True]


def test_one_far_worse_map_saturates_instead_of_darkening_the_others():
    from fwk.evaluation.render import _cells, _shared_clims

    V, _ = sphere(1)
    maps = [np.linspace(0, 1, len(V)), np.linspace(0, 1.2, len(V)), np.linspace(0, 40, len(V))]
    cells = _cells([[{"V": V, "scalars": m, "bar": "DAME"} for m in maps]])
    _shared_clims(cells)
    lo, hi = cells[0][0]["clim"]
    assert lo == 0 and np.isclose(hi, np.percentile(maps[1], 99))


def test_render_rejects_unknown_view(tmp_path):
    from fwk.errors import FwkError
    from fwk.evaluation.render import render_mesh

    V, t = sphere(1)
    with pytest.raises(FwkError, match="sideways"):
        render_mesh(V, t, tmp_path / "x.png", view="sideways")


def brute_front(P):
    keep = []
    for i, p in enumerate(P):
        if not any(np.all(q <= p) and np.any(q < p) for q in P):
            keep.append(i)
    return sorted(keep, key=lambda i: P[i, 0])


def test_pareto_front_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(20):
        P = rng.integers(0, 6, (12, 2)).astype(float)  # ties and duplicates on purpose
        assert list(pareto_front(P)) == brute_front(P)
    P = np.array([[1.0, 5.0], [2.0, 2.0], [3.0, 3.0], [5.0, 1.0], [np.nan, 0.0]])
    assert list(pareto_front(P)) == [0, 1, 3]
    assert len(pareto_front(np.zeros((0, 2)))) == 0


def test_scatter_pareto_writes_png(tmp_path):
    from fwk.evaluation.plots import scatter_pareto

    pts = {f"m{i}": (x, y) for i, (x, y) in enumerate(itertools.product([1.0, 2.0], [3.0, 1.0]))}
    p = scatter_pareto(pts, tmp_path / "s.png", "L1", "DAME")
    assert p.exists() and _png(p).shape[0] > 100


def test_summarise_and_evaluate_names():
    s = summarise([1.0, 2.0, 6.0])
    assert s == {"mean": 3.0, "median": 2.0, "max": 6.0, "std": pytest.approx(np.std([1, 2, 6])), "n": 3}
    assert summarise([])["n"] == 0
    V, t = sphere(1)
    r = evaluate(V + 0.1, V, t, ["l1", "dame"])
    assert r["l1"]["scores"] == pytest.approx([0.1]) and r["l1"]["maps"].shape == (1, len(V))
    with pytest.raises(ValueError):
        evaluate(V[None], V[None, :-1], t, ["l1"])


def test_evaluate_summary_input_units():
    V, t = sphere(1)
    s = 0.05  # evaluation space = 0.05 x centimetres
    out = evaluate_summary((s * (V + 0.2))[None], (s * V)[None], t, ["l1", "l2", "euclidean", "dame"], scale=s)
    assert out["l1"]["mean_input"] == pytest.approx(0.2) and out["l1"]["units_input"] == "cm"
    assert out["l2"]["mean_input"] == pytest.approx(0.04) and out["l2"]["units_input"] == "cm^2"
    assert out["euclidean"]["mean_input"] == pytest.approx(0.2 * np.sqrt(3))
    assert out["dame"]["mean_input"] == out["dame"]["mean"] and out["dame"]["units_input"] == "rad"


def test_markdown_table_units():
    t = markdown_table([["pca", 1.5]], ["model", "l1"], units={"l1": "cm"})
    assert t.splitlines()[0] == "| model | l1 (cm) |" and t.splitlines()[2] == "| pca | 1.5 |"
    with pytest.raises(ValueError):
        markdown_table([["a"]], ["x"], units=["u", "v"])


def test_write_report_relative_figures_and_json(tmp_path, monkeypatch):
    from fwk.evaluation.plots import scatter_pareto

    run = tmp_path / "runs" / "r1"
    ctx = _Dir(run)
    V, t = sphere(1)
    res = {"models": {"pca": {"test": evaluate_summary((V + 0.01)[None], V[None], t, ["l1", "l2", "dame"], 0.5)}},
           "dataset": {"name": "sphere", "units": "cm"}}
    fig = scatter_pareto({"pca": (1, 2), "vae": (2, 1)}, ctx.path("figures", "s.png"), "L1", "DAME")
    monkeypatch.chdir(tmp_path)  # a run directory given relative to the working directory
    write_report(_Dir(__import__("pathlib").Path("runs/r1")), "T", res, {"scatter": "runs/r1/figures/s.png"})
    md = (run / "report.md").read_text()
    assert "](figures/s.png)" in md
    assert "l1 (×1e-3)" in md and "l2 (×1e-5)" in md and "dame (rad ×1e-2)" in md
    assert "l1 (cm)" in md and "l2 (cm^2)" in md
    m = json.loads((run / "metrics.json").read_text())
    assert m["figures"] == {"scatter": "figures/s.png"} and fig.exists()
    assert m["models"]["pca"]["test"]["l1"]["mean_input"] == pytest.approx(0.02)


def test_colour_limits_median_of_percentiles():
    from fwk.evaluation.render import colour_limits

    maps = [np.linspace(0, m, 101) for m in (1.0, 2.0, 50.0)]
    lo, hi = colour_limits(maps)
    assert lo == 0.0 and np.isclose(hi, np.percentile(maps[1], 99))
    assert colour_limits([np.full(5, -1.0), np.zeros(5)])[0] == -1.0
    assert colour_limits([]) == (0.0, 1.0)
    lo, hi = colour_limits([np.zeros(4), np.zeros(4)])  # all-zero maps still get a valid range
    assert hi > lo
