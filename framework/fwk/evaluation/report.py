"""``report.md`` and ``metrics.json`` of evaluating tasks, and the standard figures."""
from __future__ import annotations

import os
from pathlib import Path

from ..engine.threads import pinned, recorded_threads
from ..registry import Registry
from .core import evaluate
from .curves import training_section, training_summary
from .legend import legend_table
from .plots import scatter_pareto
from .presentation import axis_unit, display, figure_metrics
from .render import colour_limits, render_grid
from .seeds import mean_sd, seeds_note, seeds_sections
from .tables import markdown_table  # noqa: F401  (imported from here by tasks)
from .verdict import verdict_lines

SPLIT_ORDER = ("train", "val", "test")


def metric_columns(results: dict) -> list[str]:
    """The metric names of ``results["models"]``, in order of first appearance."""
    names = []
    for per_split in results.get("models", {}).values():
        for per_metric in per_split.values():
            for m in per_metric:
                if m not in names:
                    names.append(m)
    return names


def _units_of(results: dict, metric: str, key: str = "units") -> str:
    for per_split in results.get("models", {}).values():
        for per_metric in per_split.values():
            u = per_metric.get(metric, {}).get(key)
            if u:
                return u
    return ""


def results_tables(results: dict, units: str = "", registry: Registry | None = None) -> str:
    """One table per split: rows = models, columns = metrics (mean over meshes, divided by the
    metric's display factor in the header), then one table of the means in the dataset's units
    (rows = model and split) where the task recorded them. Display attributes come from the
    metric classes of ``registry`` (default: the process-wide one). A summary over several seeds
    (``seed_sd``: ``fwk.evaluation.seeds``) shows as mean ± sd over seeds."""
    out = []
    metrics = metric_columns(results)
    shown = {m: display(m, registry) for m in metrics}
    models = list(results.get("models", {}))
    seeded = any(r.get(m, {}).get("seed_sd") is not None for per in results.get("models", {}).values()
                 for r in per.values() for m in r)
    for split in _splits(results):
        cols = ["model"] + metrics
        cu = [""] + [shown[m].header_unit(_units_of(results, m)) for m in metrics]
        rows = []
        for label in models:
            r = results["models"][label].get(split, {})
            if not r:
                continue
            rows.append([label] + [mean_sd(r.get(m), shown[m].scale) for m in metrics])
        over = " (mean ± sd over seeds)" if seeded else ""
        out.append(f"### {split}: mean over meshes{over}, evaluation space\n\n" + markdown_table(rows, cols, cu))
    inp = [m for m in metrics if any("mean_input" in r.get(m, {}) for l in models
                                     for r in results["models"][l].values())]
    if inp:
        cols = ["model", "split"] + inp
        cu = ["", ""] + [_units_of(results, m, "units_input")
                         or (units + (f"^{shown[m].power}" if shown[m].power > 1 else "") if units else "")
                         for m in inp]
        rows = []
        for label in models:
            for split in _splits(results):
                r = results["models"][label].get(split)
                if r:
                    rows.append([label, split] + [mean_sd(r.get(m), suffix="_input") for m in inp])
        over = " (mean ± sd over seeds)" if seeded else ""
        out.append(f"### mean over meshes{over}, in the dataset's units\n\n" + markdown_table(rows, cols, cu))
    return "\n\n".join(out)


def _splits(results: dict) -> list[str]:
    seen = []
    for per in results.get("models", {}).values():
        for s in per:
            if s not in seen:
                seen.append(s)
    order = {s: i for i, s in enumerate(SPLIT_ORDER)}
    return sorted(seen, key=lambda s: (order.get(s, len(order)), seen.index(s)))


def write_report(ctx, title: str, results: dict, figures: dict | None = None, notes: list[str] | None = None,
                 sections: list[tuple[str, str]] | None = None, registry: Registry | None = None,
                 lead_sections: list[tuple[str, str]] | None = None, results_title: str = "Results") -> Path:
    """Write ``metrics.json`` (``results`` plus figure paths and notes) and ``report.md``.

    ``report.md`` opens with the verdict (``fwk.evaluation.verdict``: which model has the lowest
    mean on which metric and by how much, per key of ``results["verdict"]``'s section, else on
    the test split), then the dataset and notes, the legend of model labels (``results["legend"]``:
    {label: one line}, ``fwk.evaluation.legend``), ``lead_sections`` (a task's per-key tables,
    which come before any pooled one), the results per split under ``results_title``, times,
    training, ``sections`` and the figures.

    Every network the run trained (``curves/`` of the run and its sub-runs, written by
    ``fwk.engine.fit``) gets a row in the "Training" section, with epochs run, why training
    ended, the best validation loss and whether it reached a plateau, and the figure of its
    validation and train losses per epoch; metrics.json holds the same under ``training``
    (``fwk.evaluation.curves``). Without curves an earlier ``training`` in ``results`` is kept.
    Results of several seeds (``seeds`` in ``results``: ``fwk.evaluation.seeds``) add a line on
    the seeds, the comparisons over seeds with their verdicts and the per-section tables.

    ``ctx`` is a run context (or anything with ``run_dir``, ``path``, ``write_json`` and
    ``write_text``); ``registry`` gives the metrics' display attributes (default: the
    process-wide registry)."""
    figures = figures or {}
    results = dict(results)
    results["figures"] = {k: _relative(v, ctx.run_dir) for k, v in figures.items()}
    results["notes"] = list(notes or [])
    training = training_summary(ctx, lambda p: _relative(p, ctx.run_dir))
    if training is not None:
        results["training"] = training
    threads = run_threads(ctx.run_dir)
    if threads is not None:
        results["threads"] = threads[0]
    ctx.write_json("metrics.json", results)
    units = results.get("dataset", {}).get("units", "")
    parts = [f"# {title}", ""]
    verdict = verdict_lines(results, registry)
    if verdict:
        parts += [*verdict, ""]
    ds = results.get("dataset")
    if ds:
        parts.append("Dataset: " + dataset_line(ds) + "\n")
    if results.get("seeds"):
        parts.append(f"- {seeds_note(results)}")
    if threads is not None:
        parts.append(f"- Threads: {threads[0]} per process, fixed when the run started ({threads[1]}); a run's "
                     "numbers depend on its thread count, so `fwk run --threads "
                     f"{threads[0]}` reproduces them, and seeds, not thread counts, measure their spread.")
    for n in notes or []:
        parts.append(f"- {n}")
    parts.append("")
    parts.append("Metrics: l1 and l2 are the thesis's L1 and L2 norms (mean absolute / squared coordinate error), "
                 "euclidean the mean per-vertex distance; DAME and FMPD are perceptual (lower is better). "
                 "Columns show the mean divided by the factor in the header (×1e-3 means the number is in thousandths).\n")
    if results.get("legend"):
        parts.append("## Models\n\n" + legend_table(results["legend"]) + "\n")
    # a task's per-key tables, and over seeds the comparisons and per-section tables, before any pooled one
    for head, text in [*(lead_sections or []), *(seeds_sections(results, registry) if results.get("seeds") else [])]:
        parts.append(f"## {head}\n\n{text}\n")
    if results.get("models"):
        parts.append(f"## {results_title}\n")
        parts.append(results_tables(results, units, registry))
    if results.get("timing"):
        rows = [[k, *(f"{v:.3g}" for v in t.values())] for k, t in results["timing"].items()]
        cols = ["model", *next(iter(results["timing"].values())).keys()]
        parts.append("\n## Time (seconds)\n\n" + markdown_table(rows, cols))
    if results.get("training", {}).get("networks"):
        parts.append("\n## Training\n\n" + training_section(results["training"]))
    for head, text in sections or []:
        parts.append(f"\n## {head}\n\n{text}")
    if figures:
        parts.append("\n## Figures\n")
        for name, p in figures.items():
            rel = _relative(p, ctx.run_dir)
            parts.append(f"### {name}\n\n![{name}]({rel})\n")
    return ctx.write_text("report.md", "\n".join(parts) + "\n")


def run_threads(run_dir) -> tuple[int, str] | None:
    """(threads, why) the run in progress pinned (``fwk.engine.threads.pinned``), else what the
    ``versions.json`` of ``run_dir`` (or of the run it is a seed's sub-run of) recorded; None
    where neither says."""
    got = pinned()
    if got is None:
        got = recorded_threads(run_dir) or recorded_threads(Path(run_dir).parent)
    return got


def dataset_line(ds: dict) -> str:
    """The report's dataset line in words: ``name synthetic-heads, n_vertices 605, units cm,
    subjects 34 train / 2 val / 4 test`` (nested mappings written out, not as Python reprs)."""
    def words(v) -> str:
        if isinstance(v, dict):
            if v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v.values()):
                return " / ".join(f"{x:g} {k}" for k, x in v.items())
            return ", ".join(f"{k} {words(x)}" for k, x in v.items())
        if isinstance(v, (list, tuple)):
            return ", ".join(words(x) for x in v)
        if isinstance(v, float):
            return f"{v:.6g}"
        return str(v)

    return ", ".join(f"{k} {words(v)}" for k, v in ds.items())


def _relative(p, run_dir) -> str:
    """A figure path as report.md (in run_dir) must link it."""
    p, run_dir = Path(p), Path(run_dir)
    try:
        return Path(p).resolve().relative_to(run_dir.resolve()).as_posix()
    except ValueError:
        return p.as_posix() if not p.is_absolute() else os.path.relpath(p, run_dir)


def reconstruction_figures(ctx, template, stacks: dict, predictions: dict, metrics, n_rows: int = 2,
                           split: str = "test", registry: Registry | None = None, scale: float | None = None) -> dict:
    """Renders (ground truth first, then each model) with error maps of the figure metrics
    (``figure_metrics``: the point-wise distance, then the first perceptual metric, where
    ``metrics`` has them), shared colour limits per metric. With ``scale`` (the preprocessing's:
    evaluation space = ``scale`` x input) the maps are in the template's units (a metric of
    power p divided by ``scale**p``); each colour bar's title names its unit."""
    figures = {}
    distance, perceptual = figure_metrics(registry)
    names = [m.name for m in metrics]
    keys = [k for k in (distance, *perceptual[:1]) if k is not None and k in names]
    P = stacks.get(split)
    if n_rows and P is not None and len(P) and predictions:
        n = min(n_rows, len(P))
        by = {m.name: m for m in metrics}
        maps = {}
        for label, d in predictions.items():
            if split in d:
                maps[label] = evaluate(d[split][:n], P[:n], template, [by[k] for k in keys])
                if scale is not None:
                    for k in keys:
                        maps[label][k]["maps"] = maps[label][k]["maps"] / float(scale) ** by[k].power
        units_of = {k: axis_unit(by[k].units.replace("input", template.units or "input") if scale is not None
                                 else by[k].units, scale is not None) for k in keys}
        for key in keys:
            clim = colour_limits([row for l in maps for row in maps[l][key]["maps"]])
            cmap = "inferno" if key in perceptual else "viridis"
            rows = []
            for i in range(n):
                row = [{"V": P[i], "label": f"ground truth {i}"}]
                for label in maps:
                    row.append({"V": predictions[label][split][i], "scalars": maps[label][key]["maps"][i],
                                "clim": clim, "label": label, "bar": f"{key.upper()} ({units_of[key]})",
                                "cmap": cmap})
                rows.append(row)
            try:
                figures[f"{split} reconstructions with {key.upper()} error maps (front)"] = render_grid(
                    rows, template, ctx.path("figures", f"{split}_{key}_front.png"), view="front")
                figures[f"{split} reconstructions with {key.upper()} error maps (three-quarter)"] = render_grid(
                    rows, template, ctx.path("figures", f"{split}_{key}_34.png"), view="three-quarter")
            except Exception as exc:  # no OpenGL at all: report it, keep the numbers
                ctx.log(f"warning: renders skipped ({type(exc).__name__}: {exc})")
    return figures


def scatter_figure(ctx, results: dict, split: str = "test", x: str | None = None, y: str | None = None,
                   name: str | None = None, groups: dict | None = None, registry: Registry | None = None):
    """Scatter of the models' mean ``x`` against mean ``y`` on ``split`` with the Pareto front;
    None when no model has both. ``x`` and ``y`` default to the figure metrics
    (``figure_metrics``: the point-wise distance against the first perceptual metric). Each axis
    is in the dataset's units (``mean_input``) where every model has them, else in the
    evaluation space; its label says which (``L1 (test, cm)``, ``FMPD (test, unitless)``)."""
    if x is None or y is None:
        distance, perceptual = figure_metrics(registry)
        x = x if x is not None else distance
        y = y if y is not None else next(iter(perceptual), None)
    models = {label: per.get(split, {}) for label, per in results.get("models", {}).items()}
    models = {k: r for k, r in models.items() if x in r and y in r}
    if not models:
        return None
    # in the dataset's units where every model has them (runs of several scales compare there),
    # else in the evaluation space
    space = {m: "mean_input" if all("mean_input" in r[m] for r in models.values()) else "mean" for m in (x, y)}
    pts = {label: (r[x][space[x]], r[y][space[y]]) for label, r in models.items()}

    def label(m):
        u = axis_unit(_units_of(results, m, "units_input") if space[m] == "mean_input" else _units_of(results, m),
                      space[m] == "mean_input")
        return f"{m.upper()} ({split}, {u})"

    groups = {k: g for k, g in (groups or {}).items() if k in pts} or None
    return scatter_pareto(pts, ctx.path("figures", name or f"{split}_{x}_{y}_scatter.png"), label(x), label(y),
                          title=f"{x.upper()} against {y.upper()}, {split} split", groups=groups)


def standard_scatters(ctx, results: dict, split: str = "test", groups: dict | None = None,
                      registry: Registry | None = None) -> dict:
    """The standard scatter figures: the point-wise distance against each perceptual metric
    (``figure_metrics``) on ``split``, with the Pareto front; {caption: path} of those drawn."""
    distance, perceptual = figure_metrics(registry)
    figures = {}
    for y in perceptual:
        f = scatter_figure(ctx, results, split, distance, y, groups=groups, registry=registry)
        if f is not None:
            figures[f"{distance.upper()} against {y.upper()} ({split}), Pareto front dashed"] = f
    return figures
