"""The verdict that opens a report: which model wins, on which metric, by how much.

A task says what to judge with ``verdict`` in its results (metrics.json)::

    {"section": "blendshapes",       # a section {key: {label: {metric: summary}}}, e.g. per expression;
                                     # None: results["models"][label][split]
     "split": "test", "noun": "expression",
     "metrics": ["l1", "dame", "fmpd"],
     "highlight": ["pbs"],           # models whose rank is stated even when they do not win
     "judged": ["dt-0", "pbs"],      # optional: only these rows compete (others are reported, not
                                     # ranked: e.g. rows scored with the ground truth's placement)
     "not_judged_why": "...",        # optional: the reason, said once under the verdict
     "counted": "subjects"}          # what a summary's n counts (default "meshes")

Without it the verdict judges ``results["models"]`` on the test split with the figure metrics
(``figure_metrics``: the point-wise distance and the perceptual ones). Each key (expression)
gets one line: per metric the lowest mean, its value in the dataset's units where recorded, and
how far below the runner-up it lies; then each highlighted model's rank and distance from the
best. A first line counts the wins. Over several seeds (summaries with ``seed_sd``,
``fwk.evaluation.seeds``) values are mean ± sd over seeds and every margin says whether it lies
beyond the seeds' spread (the gap larger than the two sds together); a run of one seed says
"(one seed)".
"""
from __future__ import annotations

import math

from ..registry import Registry
from .presentation import display, figure_metrics
from .seeds import intervals_apart


def ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, ..., 11th, 12th, 13th, 21st."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _num(x: float) -> str:
    return f"{x:.3g}"


def _pct(p: float) -> str:
    """A percentage: whole numbers from 1 %, two significant digits below (``0.31%``)."""
    return f"{p:.0f}%" if abs(p) >= 1 or p == 0 else f"{p:.2g}%"


def _unit(units: str) -> str:
    """A value's unit as the verdict writes it after the number ("" for unitless)."""
    return "" if not units or units == "1" else f" {units}"


def _groups(results: dict, spec: dict) -> dict[str, dict]:
    """{key: {label: {metric: summary}}} that the verdict judges (only ``judged`` labels when given)."""
    judged = spec.get("judged")
    keep = (lambda label: True) if judged is None else set(judged).__contains__
    section = spec.get("section")
    if section:
        sec = results.get(section) or {}
        return {k: {lb: r for lb, r in v.items() if keep(lb)} for k, v in sec.items() if isinstance(v, dict)}
    split = spec.get("split", "test")
    rows = {label: per.get(split) for label, per in (results.get("models") or {}).items() if keep(label)}
    rows = {k: v for k, v in rows.items() if isinstance(v, dict) and v}
    return {split: rows} if rows else {}


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _value(s) -> tuple[float, float | None, str] | None:
    """(mean, sd over seeds or None, unit) of a summary, in the dataset's units where recorded;
    None for anything that is not a summary with a finite mean."""
    if not isinstance(s, dict):
        return None
    for suffix in ("_input", ""):
        if _number(s.get(f"mean{suffix}")):
            sd = s.get(f"seed_sd{suffix}")
            return float(s[f"mean{suffix}"]), (float(sd) if _number(sd) else None), str(s.get(f"units{suffix}", ""))
    return None


def _shown(v: float, sd: float | None, unit: str) -> str:
    """``0.0121 cm``, ``0.0121 ± 0.0004 cm``; a value in the evaluation space says so."""
    text = _num(v) + (f" ± {_num(sd)}" if sd is not None else "")
    if unit and "input" in unit:
        return text + " (evaluation space)"
    return text + _unit(unit)


def _apart(a: tuple, b: tuple) -> bool | None:
    """Whether (mean, sd) ``a`` and ``b`` lie apart beyond the seeds' spread (``intervals_apart``)."""
    return intervals_apart(a[0], a[1], b[0], b[1])


def verdict_lines(results: dict, registry: Registry | None = None) -> list[str]:
    """The verdict as markdown lines (the first a bold sentence, then one bullet per key); []
    when there is nothing to judge."""
    spec = dict(results.get("verdict") or {})
    groups = _groups(results, spec)
    if not groups:
        return []
    metrics = spec.get("metrics")
    if not metrics:
        distance, perceptual = figure_metrics(registry)
        metrics = [m for m in (distance, *perceptual) if m]
    highlight = [h for h in spec.get("highlight") or [] if h]
    noun = spec.get("noun", "")
    summaries = [s for rows in groups.values() for r in rows.values() if isinstance(r, dict)
                 for s in r.values() if isinstance(s, dict)]
    seeded = any(_number(s.get("seed_sd")) for s in summaries)
    n_seeds = next((s["n_seeds"] for s in summaries if _number(s.get("n_seeds"))), None)
    subjects = next((s["n"] for s in summaries if _number(s.get("n"))), None)
    wins: dict[str, int] = {}
    lines, pairs = [], 0
    for key, rows in groups.items():
        parts, ranks = [], {h: [] for h in highlight}
        for m in metrics:
            have = {lb: _value(r.get(m)) for lb, r in rows.items() if isinstance(r, dict)}
            have = {lb: v for lb, v in have.items() if v is not None}
            if not have:
                continue
            shown = display(m, registry)
            order = sorted(have, key=lambda lb: have[lb][0])
            best = order[0]
            pairs += 1
            b = have[best]
            text = f"{shown.label} `{best}` {_shown(*b)}"
            if len(order) > 1:
                ru = order[1]
                r_ = have[ru]
                if r_[0] == b[0]:
                    text += f", tied with `{ru}`"
                else:
                    wins[best] = wins.get(best, 0) + 1
                    pct = (1 - b[0] / r_[0]) * 100 if r_[0] else 0.0
                    apart = _apart(b, r_)
                    spread = "" if apart is None else (", beyond the seeds' spread" if apart
                                                       else ", within the seeds' spread")
                    text += f", {_pct(pct)} below the runner-up `{ru}`{spread}"
            else:
                wins[best] = wins.get(best, 0) + 1
            parts.append(text)
            for h in highlight:
                if h in have and h != best:
                    above = (have[h][0] / b[0] - 1) * 100 if b[0] else float("inf")
                    ranks[h].append(f"{ordinal(order.index(h) + 1)} on {shown.label} (+{_pct(above)})")
                elif h == best:
                    ranks[h].append(f"best on {shown.label}")
        if not parts:
            continue
        tail = "".join(f" `{h}`: " + ", ".join(r) + "." for h, r in ranks.items() if r)
        lines.append(f"- **{key}**: " + "; ".join(parts) + "." + tail)
    if not lines:
        return []
    spread = (f"mean ± sd over {n_seeds} seeds" if seeded and n_seeds else "one seed")  # a one-seed run says so
    who = ", ".join(f"`{lb}`'s on {n}" for lb, n in sorted(wins.items(), key=lambda kv: -kv[1]))
    per = f"{noun}-metric pairs" if noun else "metrics"
    missing = "".join(f", `{h}`'s on none" for h in highlight if h not in wins)
    split = spec.get("split", "test")
    n = f"{subjects:g} {spec.get('counted', 'meshes')}, " if subjects else ""
    head = (f"**Verdict** on the {split} split ({spread}), {n}lower is better: of {pairs} {per}, the lowest mean "
            f"is {who or 'no one'}{missing}.")
    why = spec.get("not_judged_why")
    return [head, "", *lines, *([f"- not ranked: {why}"] if why else [])]
