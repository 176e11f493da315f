"""``report.md`` and ``metrics.json`` of evaluating tasks, and the standard figures."""
from __future__ import annotations

import math
import os
from pathlib import Path

from .core import evaluate
from .plots import scatter_pareto

SPLIT_ORDER = ("train", "val", "test")


def _fmt(x, scale=1.0) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    v = x / scale
    return f"{v:.4g}"


def markdown_table(rows: list[list], columns: list[str], units=None) -> str:
    """A GitHub markdown table. ``units``: None, a list aligned with ``columns`` or a dict
    column -> unit; a unit is shown in the header as ``name (unit)`` (empty units are skipped)."""
    if units is not None:
        if isinstance(units, dict):
            units = [units.get(c, "") for c in columns]
        if len(units) != len(columns):
            raise ValueError(f"{len(units)} units for {len(columns)} columns")
        columns = [f"{c} ({u})" if u else str(c) for c, u in zip(columns, units)]
    head = "| " + " | ".join(str(c) for c in columns) + " |"
    sep = "| " + " | ".join("---" for _ in columns) + " |"
    body = ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def _scale_label(scale: float) -> str:
    if scale == 1.0:
        return ""
    e = int(round(math.log10(scale)))
    return f" ×1e{e}"


def metric_columns(results: dict) -> list[str]:
    names = []
    for per_split in results.get("models", {}).values():
        for per_metric in per_split.values():
            for m in per_metric:
                if m not in names:
                    names.append(m)
    return names


DISPLAY = {"l1": 1e-3, "l2": 1e-5, "euclidean": 1e-3, "dame": 1e-2, "fmpd": 1e-2}


def _units_of(results: dict, metric: str, key: str = "units") -> str:
    for per_split in results.get("models", {}).values():
        for per_metric in per_split.values():
            u = per_metric.get(metric, {}).get(key)
            if u:
                return u
    return ""


def _eval_unit(metric: str, units: str) -> str:
    """Header unit in the evaluation space: the thesis's display factor, and the unit unless it
    is the positions' own (the evaluation space has none: it is scaled into [-1, 1])."""
    f = _scale_label(DISPLAY.get(metric, 1.0)).strip()
    u = "" if (not units or "input" in units or units == "1") else units
    return " ".join(x for x in (u, f) if x)


def results_tables(results: dict, units: str = "") -> str:
    """One table per split: rows = models, columns = metrics (mean over meshes, divided by the
    thesis's display factor in the header), then one table of the means in the dataset's units
    (rows = model and split) where the task recorded them."""
    out = []
    metrics = metric_columns(results)
    models = list(results.get("models", {}))
    for split in _splits(results):
        cols = ["model"] + metrics
        cu = [""] + [_eval_unit(m, _units_of(results, m)) for m in metrics]
        rows = []
        for label in models:
            r = results["models"][label].get(split, {})
            if not r:
                continue
            rows.append([label] + [_fmt(r.get(m, {}).get("mean"), DISPLAY.get(m, 1.0)) for m in metrics])
        out.append(f"### {split}: mean over meshes, evaluation space\n\n" + markdown_table(rows, cols, cu))
    inp = [m for m in metrics if any("mean_input" in r.get(m, {}) for l in models
                                     for r in results["models"][l].values())]
    if inp:
        cols = ["model", "split"] + inp
        cu = ["", ""] + [_units_of(results, m, "units_input")
                         or (units + ("^2" if m == "l2" else "") if units else "") for m in inp]
        rows = []
        for label in models:
            for split in _splits(results):
                r = results["models"][label].get(split)
                if r:
                    rows.append([label, split] + [_fmt(r.get(m, {}).get("mean_input")) for m in inp])
        out.append("### mean over meshes, in the dataset's units\n\n" + markdown_table(rows, cols, cu))
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
                 sections: list[tuple[str, str]] | None = None) -> Path:
    """Write ``metrics.json`` (``results`` plus figure paths and notes) and ``report.md``."""
    figures = figures or {}
    results = dict(results)
    results["figures"] = {k: _relative(v, ctx.run_dir) for k, v in figures.items()}
    results["notes"] = list(notes or [])
    ctx.write_json("metrics.json", results)
    units = results.get("dataset", {}).get("units", "")
    parts = [f"# {title}", ""]
    ds = results.get("dataset")
    if ds:
        parts.append("Dataset: " + ", ".join(f"{k} {v}" for k, v in ds.items()) + "\n")
    for n in notes or []:
        parts.append(f"- {n}")
    parts.append("")
    parts.append("Metrics: l1 and l2 are the thesis's L1 and L2 norms (mean absolute / squared coordinate error), "
                 "euclidean the mean per-vertex distance; DAME and FMPD are perceptual (lower is better). "
                 "Columns show the mean divided by the factor in the header (×1e-3 means the number is in thousandths).\n")
    if results.get("models"):
        parts.append("## Results\n")
        parts.append(results_tables(results, units))
    if results.get("timing"):
        rows = [[k, *(f"{v:.3g}" for v in t.values())] for k, t in results["timing"].items()]
        cols = ["model", *next(iter(results["timing"].values())).keys()]
        parts.append("\n## Time (seconds)\n\n" + markdown_table(rows, cols))
    for head, text in sections or []:
        parts.append(f"\n## {head}\n\n{text}")
    if figures:
        parts.append("\n## Figures\n")
        for name, p in figures.items():
            rel = _relative(p, ctx.run_dir)
            parts.append(f"### {name}\n\n![{name}]({rel})\n")
    return ctx.write_text("report.md", "\n".join(parts) + "\n")


def _relative(p, run_dir) -> str:
    """A figure path as report.md (in run_dir) must link it."""
    p, run_dir = Path(p), Path(run_dir)
    try:
        return Path(p).resolve().relative_to(run_dir.resolve()).as_posix()
    except ValueError:
        return p.as_posix() if not p.is_absolute() else os.path.relpath(p, run_dir)


def reconstruction_figures(ctx, template, stacks: dict, predictions: dict, metrics, n_rows: int = 2,
                           split: str = "test") -> dict:
    """Renders (ground truth first, then each model with L1 and, where present, DAME error maps,
    shared colour limits) and the L1/DAME scatter with its Pareto front."""
    figures = {}
    names = [m.name for m in metrics]
    P = stacks.get(split)
    if n_rows and P is not None and len(P) and predictions:
        n = min(n_rows, len(P))
        by = {m.name: m for m in metrics}
        maps = {}
        for label, d in predictions.items():
            if split in d:
                maps[label] = evaluate(d[split][:n], P[:n], template, [by[k] for k in ("l1", "dame") if k in by])
        from .render import colour_limits

        for key in ("l1", "dame"):
            if key not in names:
                continue
            clim = colour_limits([row for l in maps for row in maps[l][key]["maps"]])
            rows = []
            for i in range(n):
                row = [{"V": P[i], "label": f"ground truth {i}"}]
                for label in maps:
                    row.append({"V": predictions[label][split][i], "scalars": maps[label][key]["maps"][i],
                                "clim": clim, "label": label, "bar": key.upper(), "cmap": "inferno" if key == "dame" else "viridis"})
                rows.append(row)
            try:
                from .render import render_grid

                figures[f"{split} reconstructions with {key.upper()} error maps (front)"] = render_grid(
                    rows, template, ctx.path("figures", f"{split}_{key}_front.png"), view="front")
                figures[f"{split} reconstructions with {key.upper()} error maps (three-quarter)"] = render_grid(
                    rows, template, ctx.path("figures", f"{split}_{key}_34.png"), view="three-quarter")
            except Exception as exc:  # no OpenGL at all: report it, keep the numbers
                ctx.log(f"warning: renders skipped ({type(exc).__name__}: {exc})")
    return figures


def scatter_figure(ctx, results: dict, split: str = "test", x: str = "l1", y: str = "dame", name: str | None = None,
                   groups: dict | None = None):
    """Scatter of the models' mean ``x`` against mean ``y`` on ``split`` with the Pareto front;
    None when no model has both."""
    pts = {}
    for label, per in results.get("models", {}).items():
        r = per.get(split, {})
        if x in r and y in r:
            pts[label] = (r[x]["mean"], r[y]["mean"])
    if not pts:
        return None
    def label(m):
        u = _eval_unit(m, _units_of(results, m)).replace(_scale_label(DISPLAY.get(m, 1.0)).strip(), "").strip()
        return f"{m.upper()} ({split}{', ' + u if u else ''})"

    groups = {k: g for k, g in (groups or {}).items() if k in pts} or None
    return scatter_pareto(pts, ctx.path("figures", name or f"{split}_{x}_{y}_scatter.png"), label(x), label(y),
                          title=f"{x.upper()} against {y.upper()}, {split} split", groups=groups)
