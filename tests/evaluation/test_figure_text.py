"""Figures a reader can read (issue 30): colour bars name their metric and unit and mark a clipped
limit with ≥, text is sized for the width a viewer shows the image at, long titles wrap, k sweeps
star the chosen k, and every blendshapes axis and colour bar carries its unit."""
import numpy as np
import pytest

from fwk.evaluation.render import _cells, _groups, _shared_clims, bar_ticks, text_px, wrap_label


def test_bar_ticks_mark_a_clipped_limit():
    ticks, labels = bar_ticks(0.0, 0.0915, clipped_high=True)
    assert ticks[0] == 0.0 and ticks[-1] == 0.0915 and labels[0] == "0" and labels[-1] == "≥ 0.0915"
    assert all(0 < t < 0.0915 * 0.82 for t in ticks[1:-1])  # round ticks keep clear of the limit's label
    _, labels = bar_ticks(-1.0, 2.0, clipped_low=True)
    assert labels[0] == "≤ -1" and labels[-1] == "2"


def test_one_bar_per_title_and_limits_knows_when_it_clips():
    V = np.zeros((50, 3))
    far = np.linspace(0, 40, 50)
    cells = _cells([[{"V": V, "scalars": np.linspace(0, 1, 50), "bar": "DAME (rad)"},
                     {"V": V, "scalars": far, "bar": "DAME (rad)"},
                     {"V": V, "scalars": np.linspace(0, 1, 50), "bar": "L1 (cm)", "clim": (0, 2)}]])
    _shared_clims(cells)
    bars = _groups(cells)
    assert [b["title"] for b in bars] == ["DAME (rad)", "L1 (cm)"]
    assert bars[0]["high"] and not bars[0]["low"] and not bars[1]["high"]


def test_text_is_sized_for_the_width_a_viewer_shows():
    assert text_px(600) == 13  # shown at its own size
    assert text_px(2100) == pytest.approx(13 * 2100 / 900)  # ~30 px: ~13 px once fitted to 900 px
    assert text_px(10_000) == 36
    lines = wrap_label("pbs:pb-euclidean-std", 12)
    assert lines[0] == "pbs:" and "".join(lines) == "pbs:pb-euclidean-std" and max(map(len, lines)) <= 12
    assert wrap_label("pbs:pb-euclidean-std", 30) == ["pbs:pb-euclidean-std"]
    assert wrap_label("ground truth", 8) == ["ground", "truth"]


def test_a_grid_png_has_readable_bands_around_the_meshes(tmp_path, monkeypatch):
    from fwk.evaluation.render import render_grid
    from fwk.testing.model import tiny_fit_data

    monkeypatch.setenv("FWK_RENDER_BACKEND", "matplotlib")
    data = tiny_fit_data(n_subjects=3, n_vertices=200)
    P = np.asarray(data.template.vertices)[None]
    s = np.linspace(0, 1, P.shape[1])
    p = render_grid([[{"V": P[0], "label": "ground truth"},
                      {"V": P[0], "scalars": s, "clim": (0, 0.5), "bar": "L1 (cm)", "label": "pbs:pb-euclidean-std"}]],
                    data.template, tmp_path / "g.png", cell_size=(200, 220))
    import matplotlib.image as mpimg

    img = mpimg.imread(str(p))
    assert img.shape[1] == 400 and img.shape[0] > 220 + 2 * 13  # a title band above, the bar below


def test_scatter_stars_the_highlighted_point_and_keeps_labels_inside(tmp_path, monkeypatch):
    from matplotlib.text import Text

    import fwk.evaluation.plots as plots

    seen = {}
    real = plots.place_labels

    def spy(ax, P, labels, **kw):
        out = real(ax, P, labels, **kw)
        seen["ax"], seen["texts"], seen["first"] = ax, out, kw.get("first")
        seen["legend"] = [t.get_text() for t in ax.get_legend().get_texts()]
        seen["x"], seen["y"] = ax.get_xlabel(), ax.get_ylabel()
        renderer = ax.figure.canvas.get_renderer()
        seen["frame"] = ax.get_window_extent(renderer)
        seen["boxes"] = [Text.get_window_extent(t, renderer) for t in out]
        return out

    monkeypatch.setattr(plots, "place_labels", spy)
    pts = {str(k): (1 + 0.01 * k, 2 - 0.012 * k + 0.00005 * k * k) for k in range(0, 400, 10)}
    plots.scatter_pareto(pts, tmp_path / "k.png", "L1 norm (validation, cm)", "FMPD (validation, unitless)",
                         highlight="120", highlight_label="chosen k = 120")
    assert "chosen k = 120" in seen["legend"] and seen["first"][0] == list(pts).index("120")
    assert seen["x"].endswith("cm)") and seen["y"].endswith("unitless)")
    frame = seen["frame"]
    for b in seen["boxes"]:
        assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
    assert seen["texts"][0].get_text() == "120"  # the chosen k is labelled first


def test_blendshapes_error_maps_and_axes_carry_units(tmp_path, monkeypatch):
    """The colour bars of the renders say metric and unit (L1 in the dataset's units: the
    evaluation-space map over the scale), and so do the k sweep's and the methods' axes."""
    import fwk_blendshapes as bs

    from fwk.plugins import get_registry
    from fwk.runs import make_test_context
    from fwk.testing.model import tiny_fit_data

    reg = get_registry()
    data = tiny_fit_data(n_subjects=4, n_vertices=200)
    G = data.stack("train")[:2]
    N = G * 0.99
    bars, axes = [], []
    monkeypatch.setattr(bs, "render_grid", lambda rows, *a, **k: bars.extend(
        (c["bar"], c["scalars"]) for row in rows for c in row if "bar" in c))
    monkeypatch.setattr(bs, "scatter_pareto", lambda pts, path, x, y, *a, **k: axes.append((x, y, k)))
    ctx = make_test_context(tmp_path)
    task = bs.Blendshapes(models={"dt": "dt"}, renders=1)
    metrics = [reg.get("metric", n)() for n in ("l1", "dame", "fmpd")]
    results = {"dataset": {"units": "cm", "scale": 0.5, "n_vertices": G.shape[1]},
               "pbs": {"pbs": {"k": {"smile": 10}, "sweep": {"smile": {
                   "ks": [0, 10], "chosen": 10, "n_subjects": 2, "l1": [0.2, 0.1], "dame": [0.3, 0.2],
                   "fmpd": [0.1, 0.2]}}}},
               "blendshapes": {"smile": {"dt": {m: {"mean": 0.1} for m in ("l1", "dame", "fmpd")}}},
               "apply_model": "dt"}
    task._figures(ctx, data.template, ["smile"], {"smile": (np.arange(2), N, G)}, {"smile": {"dt": G + 0.01}},
                  results, metrics, "l1", ["dame", "fmpd"], ["smile"])
    titles = {b for b, _ in bars}
    assert titles == {"L1 norm (cm)", "DAME (rad)"}
    l1 = next(s for b, s in bars if b == "L1 norm (cm)")
    assert np.allclose(l1, 0.01 / 0.5)  # the evaluation space's 0.01 per coordinate over the scale, in cm
    sweep = [a for a in axes if "validation" in a[0]]
    assert {(x, y) for x, y, _ in sweep} == {("L1 norm (validation, cm)", "FMPD (validation, unitless)"),
                                            ("L1 norm (validation, cm)", "DAME (validation, rad)")}
    assert all(k["highlight"] == "10" and k["highlight_label"] == "chosen k = 10" for _, _, k in sweep)
    methods = [a for a in axes if "test" in a[0]]
    assert ("L1 norm (test, cm)", "DAME (test, rad)") in {(x, y) for x, y, _ in methods}


def test_grid_sweep_plots_say_the_unit_and_the_swept_key(tmp_path, monkeypatch):
    """Figure 4.11 of a k study: each metric in the dataset's units against k, the axes saying so."""
    import fwk_grid

    from fwk.runs import make_test_context

    seen = []
    monkeypatch.setattr(fwk_grid, "line_plot", lambda series, path, x, y, **k: seen.append((x, y, series)) or path)
    g = fwk_grid.Grid(base="b.yaml", configs={"k10": {}, "k40": {}}, sweep="models.dsm.k", columns=["l1", "fmpd"])
    res = {"models": {m: {s: {"l1": {"mean": v, "mean_input": v / 0.5, "units": "input", "units_input": "cm"},
                               "fmpd": {"mean": v, "mean_input": v, "units": "1", "units_input": "1"}}
                           for s in ("train", "test")} for m, v in (("k10", 0.1), ("k40", 0.2))}}
    g._sweep_figures(make_test_context(tmp_path), res, {"k10": 10.0, "k40": 40.0})
    labels = {(x, y) for x, y, _ in seen}
    assert labels == {("k (models.dsm.k, log scale)", "L1 norm (cm)"), ("k (models.dsm.k, log scale)", "FMPD (unitless)")}
    l1 = next(s for _, y, s in seen if y == "L1 norm (cm)")
    assert l1["test"] == ([10.0, 40.0], [0.2, 0.4])  # in cm: the evaluation space over the scale
