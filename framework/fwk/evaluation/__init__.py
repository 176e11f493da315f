"""Evaluation: metrics over batches, summaries, reports (``report.md``, ``metrics.json``) and
pictures (renders with error maps, L1/DAME scatter with the Pareto front).

API (tasks call these)::

    evaluate(pred, target, template, metrics) -> {name: {"scores": (b,), "maps": (b, n)}}
    evaluate_summary(pred, target, template, metrics, scale=1.0) -> {name: summary}
    summarise(scores) -> {"mean", "median", "max", "std", "n"}
    pareto_front(points (k, 2)) -> indices of the non-dominated points (both minimised)
    markdown_table(rows, columns, units=None) -> str
    write_report(ctx, title, results, figures=None, notes=None, sections=None, registry=None) -> report.md path
    standard_scatters(ctx, results, split="test", groups=None, registry=None) -> {caption: path}
    render.render_mesh / render.render_grid, plots.scatter_pareto / plots.line_plot

How metrics are shown comes from the metric classes (``label``, ``display_scale``, ``units``,
``power``, ``default``, ``default_rank``; see ``fwk.protocols.Metric``), never from a list here::

    default_metrics(registry=None) -> [name, ...]   # default = True, in default_rank order
    display(metric, registry=None) -> Display(scale, label, units, name, power)
                                       # .suffix " ×1e-3", .format(x), .header_unit(units)
    figure_metrics(registry=None) -> (distance, [perceptual, ...])
    format_value(x, scale=1.0) -> str; scale_suffix(scale) -> str

metrics.json schema (every evaluating task writes it; ``fwk report`` reads it)::

    {"models": {label: {split: {metric: {
         "mean", "median", "max", "std", "n",       # per-mesh scores summarised, evaluation space
         "units",                                   # "input", "input^2", "rad", "1"
         "mean_input", "median_input", "max_input", "std_input",   # the same in dataset units
         "units_input"}}}},                         # e.g. "cm", "cm^2", "rad", "1"
     "dataset": {"name", "units", ...},             # optional, shown at the top of report.md
     "timing": {label: {name: seconds}},            # optional
     "figures": {caption: path relative to the run directory},
     "notes": [str, ...],
     "training": {network: {"epochs", "ended_by", "best_val", "best_epoch", "plateau", ...}}}
                                                    # from curves/ (fwk.evaluation.curves); tasks may
                                                    # add more top-level keys
     "comparisons": [{"a": key path, "b": key path, "metric", "about", "a_name", "b_name"}],
                                                    # optional: the report's "A beats B" statements
     "verdict": {"section", "split", "noun", "metrics", "highlight", "counted"},
                                                    # optional: what the opening verdict judges
                                                    # (fwk.evaluation.verdict; default: the test split)
     "legend": {label: one line}}                   # optional: the report's "Models" table
                                                    # (fwk.evaluation.legend)

A run of several seeds (``seeds:``; ``fwk.seeds``, ``fwk.evaluation.seeds``) combines its seeds'
metrics.json: each summary also has ``seed_sd``, ``seed_means`` ({seed: mean}), ``n_seeds`` (and
``seed_sd_input``, ``seed_means_input``), ``mean`` being the mean over seeds; top-level ``seeds``,
``split_seed``, ``seed_runs`` and ``seed_comparisons`` (each comparison with its per-seed
Wilcoxon p-values and verdict). Tasks write the per-subject test scores behind each mean to
``scores.json``, at the summary's key path (``evaluate_summary(..., scores_out=)``).

The evaluation space is the registered data scaled by s into [-1, 1] (the thesis's space);
input-unit values divide l1 and euclidean by s and l2 by s^2; DAME and FMPD are
scale-invariant, so their input-unit values equal the evaluation-space ones.
"""
from .core import TopologyMemo, evaluate, evaluate_summary, pareto_front, summarise  # noqa: F401
from .presentation import (Display, default_metrics, display, figure_metrics, format_value,  # noqa: F401
                           scale_suffix)
from .report import (markdown_table, reconstruction_figures, scatter_figure, standard_scatters,  # noqa: F401
                     write_report)
