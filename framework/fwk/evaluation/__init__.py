"""Evaluation: metrics over splits, summaries, reports (``report.md``, ``metrics.json``) and
pictures (renders with error maps, L1/DAME scatter with the Pareto front).

metrics.json schema (every evaluating task)::

    {"models": {label: {split: {metric: {"mean", "median", "max", "std", "units",
                                         "mean_input", "units_input"}}}},
     "dataset": {...}, "timing": {label: {...}}, "notes": [...], "figures": {...}}

Numbers are in the evaluation space (registered, scaled into [-1, 1]: the thesis's space);
``*_input`` repeat them in the dataset's units (l1, euclidean divided by the scale s, l2 by
s^2; DAME and FMPD are scale-invariant).
"""
from .core import evaluate, evaluate_summary, pareto_front, summarise  # noqa: F401
from .report import markdown_table, reconstruction_figures, write_report  # noqa: F401
