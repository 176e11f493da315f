"""Runs of several seeds: the seeds' metrics as mean ± sd, and every comparison tested.

A run of a recipe with ``seeds:`` (``fwk.seeds``) holds one complete sub-run per seed,
``<run>/seed-<s>/``, all on one split; each has its own ``metrics.json``, ``report.md`` and
``scores.json`` (the per-subject test scores behind every mean, at the same key path as the
summary in ``metrics.json``). ``seeds_results`` combines them into the run's ``metrics.json``:

* every summary (``{"mean", "n", "units", ...}``) becomes ``mean`` (the mean over seeds of the
  seeds' means; ``median``, ``max``, ``std`` and the ``*_input`` values likewise), ``seed_sd``
  (the sample standard deviation over seeds of the seeds' means, n - 1 in the denominator; None
  with one seed), ``seed_means`` ({seed: that seed's mean}), ``n_seeds``, and the same
  ``seed_sd_input`` / ``seed_means_input`` in the dataset's units;
* any other value is kept where every seed has the same, else it becomes ``{"by_seed":
  {seed: value}}`` (a PBS's k per expression, for instance); ``timing`` is the mean per seed;
* ``seeds`` lists the seeds, ``split_seed`` the split's seed, ``seed_runs`` the sub-runs;
* ``seed_comparisons``: every comparison a seed's report states (its ``comparisons``: "A beats
  B" on one metric) restated over the seeds and tested (``compare``, the rule ``RULE``).

``report.md`` (``fwk.evaluation.write_report``, also on ``fwk report RUN``) shows each number as
mean ± sd, the comparisons as sentences with their verdict, and the seeds' per-section tables.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .presentation import display, format_value
from .tables import markdown_table

#: the significance level of the per-seed paired test
ALPHA = 0.05
#: the per-seed sub-run of seed s
SEED_DIR = "seed-{}"
#: the rule every "A beats B" verdict over seeds follows, as reports and docs state it
RULE = ("A beats B beyond the seeds' spread when both hold: (1) on every seed, a two-sided Wilcoxon "
        f"signed-rank test of the test subjects' paired scores (A's against B's, on the same subjects) gives "
        f"p < {ALPHA:g}, with A's mean the lower; (2) the intervals mean ± sd over seeds of A and of B do not "
        "overlap (B's mean - A's mean > sd of A + sd of B; sd: the sample standard deviation of the seeds' "
        "means). Otherwise the lower mean is named with what failed; a comparison resting on one seed says "
        "(one seed).")
SUMMARY_KEYS = ("mean", "median", "max", "std")


# ------------------------------------------------------------------------- aggregation

def is_summary(d) -> bool:
    """Whether ``d`` is a metric summary of ``fwk.evaluation.evaluate_summary``."""
    return isinstance(d, dict) and "mean" in d and "n" in d and "units" in d


def _sd(values: list[float]) -> float | None:
    """The sample standard deviation (n - 1); None for fewer than two values."""
    v = [x for x in values if x is not None]
    if len(v) < 2:
        return None
    if all(x == v[0] for x in v):  # exactly 0, not the rounding of the mean (a closed-form model's)
        return 0.0
    return float(np.std(np.asarray(v, dtype=np.float64), ddof=1))


def _mean(values: list) -> float | None:
    """The mean; equal values give that value exactly."""
    v = [x for x in values if x is not None]
    if not v:
        return None
    if all(x == v[0] for x in v):
        return float(v[0])
    return float(np.mean(np.asarray(v, dtype=np.float64)))


def aggregate_summaries(per_seed: dict) -> dict:
    """One summary over seeds from {seed: summary} (see the module docstring)."""
    first = next(iter(per_seed.values()))
    out = {k: first[k] for k in ("units", "units_input", "n") if k in first}
    for suffix in ("", "_input"):
        if f"mean{suffix}" not in first:
            continue
        for k in SUMMARY_KEYS:
            key = f"{k}{suffix}"
            if all(key in s for s in per_seed.values()):
                out[key] = _mean([s[key] for s in per_seed.values()])
        means = {str(seed): s.get(f"mean{suffix}") for seed, s in per_seed.items()}
        out[f"seed_sd{suffix}"] = _sd(list(means.values()))
        out[f"seed_means{suffix}"] = means
    out["n_seeds"] = len(per_seed)
    return out


def aggregate(per_seed: dict):
    """{seed: value} of one key path of the seeds' metrics.json, combined (module docstring)."""
    values = list(per_seed.values())
    if all(is_summary(v) for v in values):
        return aggregate_summaries(per_seed)
    if all(isinstance(v, dict) for v in values) and not any(is_summary(v) for v in values):
        keys = list(dict.fromkeys(k for v in values for k in v))
        out = {}
        for k in keys:
            have = {s: v[k] for s, v in per_seed.items() if k in v}
            out[k] = aggregate(have) if len(have) == len(per_seed) else {"by_seed": {str(s): x for s, x in have.items()}}
        return out
    if all(v == values[0] for v in values[1:]):
        return values[0]
    return {"by_seed": {str(s): v for s, v in per_seed.items()}}


def _get(tree, path):
    for p in path:
        if not isinstance(tree, dict) or p not in tree:
            return None
        tree = tree[p]
    return tree


# ------------------------------------------------------------------------- the test

def paired_test(a, b) -> dict:
    """Two-sided Wilcoxon signed-rank test of paired scores ``a`` and ``b`` (one per test
    subject, the same subjects in the same order): ``{"n": pairs, "n_nonzero": pairs that differ,
    "p": p-value, "mean_a", "mean_b"}``. Pairs with equal scores are dropped (Wilcoxon's
    treatment); no differing pair gives p = 1. scipy.stats.wilcoxon computes it: the exact null
    distribution for up to 50 differing pairs without tied differences, else its normal
    approximation."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"paired scores of shapes {a.shape} and {b.shape}: expected two equal 1-d arrays")
    d = a - b
    nz = int(np.count_nonzero(d[np.isfinite(d)]))
    out = {"n": int(a.size), "n_nonzero": nz, "mean_a": float(a.mean()) if a.size else None,
           "mean_b": float(b.mean()) if b.size else None}
    if not np.all(np.isfinite(d)):
        out["p"] = None
        return out
    if nz == 0:
        out["p"] = 1.0
        return out
    # deferred: scipy.stats costs ~1-2 s of import time (python -X importtime) that `fwk --help`
    # and every run without seeds need not pay
    from scipy.stats import wilcoxon

    out["p"] = float(wilcoxon(a, b, zero_method="wilcox", alternative="two-sided").pvalue)
    return out


def min_pairs(alpha: float = ALPHA) -> int:
    """The fewest paired subjects for which the two-sided exact Wilcoxon signed-rank test can
    give p < ``alpha`` (its smallest p-value is 2 / 2^n: all differences of one sign)."""
    n = 1
    while 2.0 / 2 ** n >= alpha:
        n += 1
    return n


def intervals_apart(ma: float, sa: float | None, mb: float, sb: float | None) -> bool | None:
    """Whether the intervals mean ± sd of A and B do not overlap: |mb - ma| > sa + sb; None
    without both sds (one seed: no spread to compare with)."""
    if sa is None or sb is None:
        return None
    return abs(mb - ma) > sa + sb


def compare(a_scores: dict, b_scores: dict, a_means: dict | None = None, b_means: dict | None = None) -> dict:
    """Whether A beats B over seeds (``RULE``). ``a_scores``, ``b_scores``: {seed: per-subject
    scores}; ``a_means``, ``b_means``: {seed: the seed's mean} (default: the scores' means).

    Returns ``{"mean_a", "sd_a", "mean_b", "sd_b", "per_seed": {seed: {"mean_a", "mean_b", "p",
    "n"}}, "n_seeds", "lower": "a" | "b" | "tie", "significant": seeds with p < ALPHA and the
    overall lower one lower, "apart": intervals do not overlap, "verdict": "a" | "b" (beats
    beyond the spread) | None}``; with one seed ``verdict`` is None and ``one_seed`` True."""
    seeds = [s for s in a_scores if s in b_scores]
    per = {}
    for s in seeds:
        t = paired_test(a_scores[s], b_scores[s])
        ma = (a_means or {}).get(s, t["mean_a"])
        mb = (b_means or {}).get(s, t["mean_b"])
        per[str(s)] = {"mean_a": ma, "mean_b": mb, "p": t["p"], "n": t["n"]}
    ma = _mean([v["mean_a"] for v in per.values()])
    mb = _mean([v["mean_b"] for v in per.values()])
    sa = _sd([v["mean_a"] for v in per.values()])
    sb = _sd([v["mean_b"] for v in per.values()])
    lower = "tie" if ma is None or mb is None or ma == mb else ("a" if ma < mb else "b")
    out = {"mean_a": ma, "sd_a": sa, "mean_b": mb, "sd_b": sb, "per_seed": per, "n_seeds": len(per),
           "lower": lower, "one_seed": len(per) == 1}
    if lower == "tie":
        out.update(significant=0, apart=False, verdict=None)
        return out

    def seed_lower(v):
        return v["mean_a"] < v["mean_b"] if lower == "a" else v["mean_b"] < v["mean_a"]

    out["significant"] = sum(1 for v in per.values() if v["p"] is not None and v["p"] < ALPHA and seed_lower(v))
    out["apart"] = bool(intervals_apart(ma, sa, mb, sb))
    out["verdict"] = lower if (len(per) >= 2 and out["significant"] == len(per) and out["apart"]) else None
    return out


# ------------------------------------------------------------------------- the run

def seed_runs(run_dir, seeds) -> dict[int, Path]:
    """{seed: its sub-run folder}."""
    return {int(s): Path(run_dir) / SEED_DIR.format(s) for s in seeds}


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def seeds_results(run_dir, seeds, split_seed: int | None = None) -> dict:
    """The run's metrics.json from its seeds' sub-runs (module docstring)."""
    runs = seed_runs(run_dir, seeds)
    metrics = {s: _read(p / "metrics.json") for s, p in runs.items()}
    scores = {s: _read(p / "scores.json") for s, p in runs.items()}
    skip = ("figures", "notes", "training", "timing", "comparisons")
    keys = list(dict.fromkeys(k for m in metrics.values() for k in m if k not in skip))
    out = {}
    for k in keys:
        have = {s: m[k] for s, m in metrics.items() if k in m}
        out[k] = aggregate(have) if len(have) == len(metrics) else {"by_seed": {str(s): v for s, v in have.items()}}
    timing = {s: m.get("timing") for s, m in metrics.items() if isinstance(m.get("timing"), dict)}
    if timing:
        labels = list(dict.fromkeys(lb for t in timing.values() for lb in t))
        out["timing"] = {lb: {k: _mean([t.get(lb, {}).get(k) for t in timing.values()])
                              for k in dict.fromkeys(k for t in timing.values() for k in t.get(lb, {}))}
                         for lb in labels}
    out["seeds"] = [int(s) for s in seeds]
    if split_seed is not None:
        out["split_seed"] = int(split_seed)
    out["seed_runs"] = {str(s): p.name for s, p in runs.items()}
    out["seed_comparisons"] = comparisons(metrics, scores)
    return out


def comparisons(metrics: dict, scores: dict) -> list[dict]:
    """Every comparison the seeds' reports state (the first seed's ``comparisons``, in its
    order), restated over the seeds (``compare``); a comparison without per-subject scores on
    some seed is listed without a test (``p`` None)."""
    first = next(iter(metrics.values()), {})
    out = []
    for c in first.get("comparisons", []):
        m = c["metric"]
        a_sc, b_sc, a_mean, b_mean = {}, {}, {}, {}
        for s in metrics:
            sa, sb = _get(metrics[s], c["a"]), _get(metrics[s], c["b"])
            if not (isinstance(sa, dict) and isinstance(sb, dict) and m in sa and m in sb):
                continue
            a_mean[s], b_mean[s] = sa[m]["mean"], sb[m]["mean"]
            xa, xb = _get(scores[s], [*c["a"], m]), _get(scores[s], [*c["b"], m])
            ok = isinstance(xa, list) and isinstance(xb, list) and len(xa) == len(xb)
            a_sc[s], b_sc[s] = (xa, xb) if ok else ([float("nan")], [float("nan")])
        if not a_mean:
            continue
        out.append({**c, **compare(a_sc, b_sc, a_mean, b_mean)})
    return out


# ------------------------------------------------------------------------- the report

def mean_sd(summary: dict | None, scale: float = 1.0, suffix: str = "") -> str:
    """A table cell: ``mean ± sd`` over seeds (``mean`` alone for one seed or no seeds)."""
    if not summary:
        return "n/a"
    m = format_value(summary.get(f"mean{suffix}"), scale)
    sd = summary.get(f"seed_sd{suffix}")
    if sd is None:
        return m
    return f"{m} ± {format_value(sd, scale)}"


def _pct(a, b) -> str:
    if a is None or b is None or not b:
        return ""
    return f"{abs(1 - a / b) * 100:.0f}% {'lower' if a < b else 'higher'}"


def sentence(c: dict, registry=None) -> str:
    """One comparison as a report sentence with its verdict (``RULE``)."""
    shown = display(c["metric"], registry)
    a, b = c.get("a_name") or c["a"][-1], c.get("b_name") or c["b"][-1]
    head = f"{c.get('about', '')}, {shown.label}: " if c.get("about") else f"{shown.label}: "
    va = format_value(c["mean_a"], shown.scale) + (f" ± {format_value(c['sd_a'], shown.scale)}" if c["sd_a"] is not None else "")
    vb = format_value(c["mean_b"], shown.scale) + (f" ± {format_value(c['sd_b'], shown.scale)}" if c["sd_b"] is not None else "")
    unit = f" ({shown.suffix.strip()})" if shown.suffix else ""
    ps = [v["p"] for v in c["per_seed"].values()]
    ptext = ", ".join("n/a" if p is None else f"{p:.3g}" for p in ps)
    values = f"`{a}` {va} against `{b}` {vb}{unit}"
    if c["lower"] == "tie":
        return f"- {head}{values}: equal means, no winner" + (" (one seed)" if c["one_seed"] else "") + "."
    win, lose = (a, b) if c["lower"] == "a" else (b, a)
    pct = _pct(c["mean_a"], c["mean_b"]) if c["lower"] == "a" else _pct(c["mean_b"], c["mean_a"])
    if c["one_seed"]:
        return (f"- {head}{values}: `{win}` beats `{lose}` on the means ({pct}; Wilcoxon p = {ptext} over "
                f"{next(iter(c['per_seed'].values()))['n']} test subjects) (one seed).")
    n = c["n_seeds"]
    if c["verdict"]:
        return (f"- {head}{values}: `{win}` beats `{lose}` beyond the seeds' spread ({pct}; p < {ALPHA:g} "
                f"on {n} of {n} seeds: p = {ptext}; intervals apart).")
    why = []
    if c["significant"] < n:
        pairs = min(v["n"] for v in c["per_seed"].values())
        few = (f", and {pairs} test subjects cannot give p < {ALPHA:g} (at least {min_pairs()} needed)"
               if pairs < min_pairs() else "")
        why.append(f"p < {ALPHA:g} with `{win}` lower on {c['significant']} of {n} seeds (p = {ptext}){few}")
    if not c["apart"]:
        why.append("the mean ± sd intervals overlap")
    return f"- {head}{values}: `{win}` is lower on average ({pct}), not beyond the seeds' spread: " \
           + "; ".join(why) + "."


def per_section_tables(results: dict, registry=None) -> list[tuple[str, str]]:
    """A table per section of the form {key: {row: {metric: summary}}} (a blendshapes run's
    per-expression results): rows key x metric, a column per row label, cells mean ± sd."""
    out = []
    for name, sec in results.items():
        if name == "models" or not isinstance(sec, dict) or not sec:
            continue
        if not all(isinstance(v, dict) and v and all(isinstance(r, dict) and r and all(is_summary(x) for x in r.values())
                                                     for r in v.values()) for v in sec.values()):
            continue
        rows = list(dict.fromkeys(r for v in sec.values() for r in v))
        metrics = list(dict.fromkeys(m for v in sec.values() for r in v.values() for m in r))
        body = []
        for key, v in sec.items():
            for m in metrics:
                shown = display(m, registry)
                body.append([key, f"{shown.label}{shown.suffix}",
                             *(mean_sd(v.get(r, {}).get(m), shown.scale) for r in rows)])
        out.append((f"{name}: mean ± sd over seeds (test)",
                    "Mean over seeds of each seed's mean over test subjects ± the sample sd over seeds, "
                    "evaluation space; lower is better.\n\n" + markdown_table(body, [name, "metric", *rows])))
    return out


def seeds_note(results: dict) -> str:
    """The report's line on the seeds."""
    seeds = results.get("seeds") or []
    runs = results.get("seed_runs") or {}
    where = ", ".join(f"`{v}/report.md`" for v in runs.values())
    split = f" (split seed {results['split_seed']})" if "split_seed" in results else ""
    return (f"{len(seeds)} seed{'s' if len(seeds) != 1 else ''} ({', '.join(map(str, seeds))}): every model trained once per seed on one split{split}; "
            f"each number is the mean over seeds ± the sample standard deviation over seeds (n - 1)"
            + (" (one seed: no sd)" if len(seeds) == 1 else "")
            + f"; times are the mean per seed; each seed's own report: {where}")


def seeds_sections(results: dict, registry=None) -> list[tuple[str, str]]:
    """The report sections of a run of several seeds: the comparisons with their verdicts, then
    the per-section tables."""
    out = []
    comps = results.get("seed_comparisons") or []
    if comps:
        out.append(("Comparisons over seeds (test)", RULE + "\n\n" + "\n".join(sentence(c, registry) for c in comps)))
    return out + per_section_tables(results, registry)
