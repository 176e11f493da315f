"""The training curves of a run in its report: did every network converge?

``fwk.engine.fit`` writes, for every network it trains, ``curves/<label>/<name>.json`` in the
run directory (per-epoch train and validation losses, why training ended). This module finds
them (sub-runs included: a grid's members, edit's ``reconstruct/``), summarises each network,
draws the curves, and writes the report's "Training" section and metrics.json's ``training``.

A network is on a **plateau** when its best validation loss improved by less than
``PLATEAU_THRESHOLD`` (1 %, relative) over the last ``w`` epochs it trained, where ``w`` is
10 % of the epochs run but at least 5: with v_e the validation loss of epoch e and E epochs,
``(min(v_1..v_{E-w}) - min(v_1..v_E)) / min(v_1..v_{E-w}) < 0.01``. Fewer than ``w + 1``
epochs cannot tell.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

from .tables import markdown_table

PLATEAU_THRESHOLD = 0.01
PLATEAU_MIN_WINDOW = 5
PLATEAU_WINDOW_FRACTION = 0.1
NETWORKS_PER_FIGURE = 8

PLATEAU_RULE = (f"A network is on a plateau when its best validation loss improved by less than "
                f"{PLATEAU_THRESHOLD:.0%} (relative) over its last w epochs, w = {PLATEAU_WINDOW_FRACTION:.0%} of the "
                f"epochs it ran but at least {PLATEAU_MIN_WINDOW}: (min over epochs 1..E-w - min over 1..E) / "
                f"min over 1..E-w < {PLATEAU_THRESHOLD:g}; fewer than w + 1 epochs cannot tell.")

#: folders of a run directory that never hold training curves (not searched)
_SKIP = {"checkpoints", "tb", "predictions", "figures", "stats", "models"}


def find_curves(run_dir) -> dict[str, dict]:
    """{network: record} of every ``curves/**.json`` under ``run_dir`` (sub-runs prefixed by
    their folder), in path order; unreadable files are skipped."""
    run_dir = Path(run_dir)
    found = {}
    if not run_dir.is_dir():
        return found
    for here, dirs, _files in os.walk(run_dir):
        dirs[:] = sorted(d for d in dirs if d not in _SKIP and not d.startswith("."))
        if "curves" not in dirs:
            continue
        dirs.remove("curves")
        prefix = Path(here).relative_to(run_dir).as_posix()
        for p in sorted((Path(here) / "curves").rglob("*.json")):
            try:
                rec = json.loads(p.read_text())
            except (OSError, ValueError):
                continue
            if not isinstance(rec, dict) or not rec.get("epochs"):
                continue
            name = rec.get("network") or p.relative_to(Path(here) / "curves").with_suffix("").as_posix()
            found[name if prefix == "." else f"{prefix}/{name}"] = rec
    return found


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def plateau(values: list) -> dict:
    """The plateau test (module docstring) on the validation losses of epochs 1..E:
    {window, improvement (relative, None when it cannot tell), verdict: plateau / improving /
    too few epochs / no validation}."""
    E = len(values)
    w = max(PLATEAU_MIN_WINDOW, math.ceil(PLATEAU_WINDOW_FRACTION * E))
    if not values or not any(_finite(v) for v in values):
        return {"window": w, "improvement": None, "verdict": "no validation"}
    if E <= w:
        return {"window": w, "improvement": None, "verdict": "too few epochs"}
    before = [v for v in values[:E - w] if _finite(v)]
    if not before:
        return {"window": w, "improvement": None, "verdict": "too few epochs"}
    ref, best = min(before), min(v for v in values if _finite(v))
    rel = (ref - best) / abs(ref) if ref != 0 else (0.0 if best == ref else math.inf)
    return {"window": w, "improvement": rel, "verdict": "plateau" if rel < PLATEAU_THRESHOLD else "improving"}


def _epoch_seconds(epochs: list):
    secs = [e.get("seconds") for e in epochs]
    return round(sum(secs), 3) if secs and all(_finite(v) for v in secs) else None


def summarise(record: dict) -> dict:
    """One network's row: epochs run and the maximum, why training ended, the best validation
    loss and its epoch, the last one, the plateau test, and ``train_s``: the sum of the epochs'
    own seconds (a resumed run's earlier epochs included, unlike the task's ``timing.fit_s``,
    which counts the last attempt; None when an epoch has no time)."""
    monitor = record.get("monitor") or "val_loss"
    val = [e.get(monitor) for e in record["epochs"]]
    out = {
        "epochs_run": record.get("epochs_run", len(record["epochs"])),
        "max_epochs": record.get("max_epochs"),
        "finished": bool(record.get("finished")),
        "stopped_by": record.get("stopped_by"),
        "stopped_epoch": record.get("stopped_epoch"),
        "early_stopping": record.get("early_stopping"),
        "monitor": monitor,
        "best_val_loss": record.get("best_val_loss"),
        "best_epoch": record.get("best_epoch"),
        "last_val_loss": val[-1] if val else None,
        "last_train_loss": record["epochs"][-1].get("train_loss"),
        "train_s": _epoch_seconds(record["epochs"]),
    }
    p = plateau(val)
    out.update(plateau_window=p["window"], plateau_improvement=p["improvement"], plateau=p["verdict"])
    return out


def curves_figures(records: dict, path) -> list[Path]:
    """The validation (solid) and train (dashed) loss per epoch of every network, log scale,
    the best validation epoch ringed; ``NETWORKS_PER_FIGURE`` networks a figure (``path``,
    then ``<stem>-2.png``...)."""
    from matplotlib.ticker import MaxNLocator

    from .plots import _plt, _ticks, save_figure  # deferred: pyplot costs ~0.5 s of import time

    plt = _plt()
    path = Path(path)
    names = list(records)
    out = []
    for k in range(0, len(names), NETWORKS_PER_FIGURE):
        chunk = names[k:k + NETWORKS_PER_FIGURE]
        fig, ax = plt.subplots(figsize=(7.2, 4.6), dpi=120)
        cmap = plt.get_cmap("tab10")
        positive = True
        for i, name in enumerate(chunk):
            rec = records[name]
            monitor = rec.get("monitor") or "val_loss"
            ep = [e["epoch"] for e in rec["epochs"]]
            tr = [e.get("train_loss") for e in rec["epochs"]]
            va = [e.get(monitor) for e in rec["epochs"]]
            colour = cmap(i % 10)
            if any(_finite(v) for v in va):
                ax.plot(ep, [v if _finite(v) else math.nan for v in va], "-", color=colour, label=f"{name} (val)")
                if rec.get("best_epoch"):
                    ax.plot([rec["best_epoch"]], [rec["best_val_loss"]], "o", ms=7, mfc="none", color=colour)
            if any(_finite(v) for v in tr):
                ax.plot(ep, [v if _finite(v) else math.nan for v in tr], "--", color=colour, alpha=0.7,
                        label=f"{name} (train)")
            positive &= all(v > 0 for v in va + tr if _finite(v))
        if positive:
            ax.set_yscale("log")
        _ticks(ax)  # plain log ticks (0.03, 0.05), no 3.3 x 10^-2 on every line
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # whole epochs, never 1.2
        ax.set_xlabel("epoch (count)")
        ax.set_ylabel("loss (each network's objective as logged, unitless)")
        ax.set_title("Training curves: validation solid, train dashed, best validation epoch ringed", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        p = path if k == 0 else path.with_name(f"{path.stem}-{k // NETWORKS_PER_FIGURE + 1}{path.suffix}")
        out.append(save_figure(fig, p))
    return out


def training_summary(ctx, relative) -> dict | None:
    """metrics.json's ``training``: the plateau rule, one summary per network, the figures
    (paths made relative by ``relative(path)``); None when the run trained no network."""
    records = find_curves(ctx.run_dir)
    if not records:
        return None
    out = {"plateau_rule": PLATEAU_RULE, "networks": {n: summarise(r) for n, r in records.items()}, "figures": []}
    try:
        out["figures"] = [relative(p) for p in curves_figures(records, ctx.path("figures", "training_curves.png"))]
    except Exception as exc:  # no matplotlib backend at all: keep the numbers
        out["figure_error"] = f"{type(exc).__name__}: {exc}"
    return out


def _fmt(v) -> str:
    from .presentation import format_value

    return format_value(v) if _finite(v) else "-"


def _ended(s: dict) -> str:
    if s["stopped_by"] == "early_stopping":
        return f"rule, epoch {s['stopped_epoch']}"
    if s["stopped_by"] == "max_epochs":
        return "max epochs"
    return "not finished"


def training_section(training: dict) -> str:
    """The report's "Training" section: the table, the plateau rule, the figures."""
    from ..engine.callbacks import duration  # deferred: the engine imports Lightning

    rows = []
    for name, s in training["networks"].items():
        imp = s["plateau_improvement"]
        rows.append([name, f"{s['epochs_run']} / {s['max_epochs']}", _ended(s), _fmt(s["best_val_loss"]),
                     s["best_epoch"] if s["best_epoch"] is not None else "-", _fmt(s["last_val_loss"]),
                     f"{imp:.2%}" if _finite(imp) else "-", s["plateau_window"], s["plateau"],
                     duration(s["train_s"]) if _finite(s.get("train_s")) else "-"])
    cols = ["network", "epochs run / max", "ended by", "best val loss", "best epoch", "last val loss",
            "improvement, last w epochs", "w", "verdict", "training time"]
    rules = {json.dumps(s["early_stopping"], sort_keys=True) for s in training["networks"].values()
             if s.get("early_stopping")}
    parts = [markdown_table(rows, cols), "",
             "Losses as each network logs them (its own units and terms). " + training["plateau_rule"]
             + " Training time: the sum of the epochs' own seconds (training and validation; a resumed run's "
               "earlier epochs included)."]
    if rules:
        parts.append("Stopping rule (train.early_stopping): " + "; ".join(
            f"stop after {r['patience']} epochs in a row without a {r['monitor']} below the best by more than "
            + (f"{r['min_delta']:g} of it" if r.get("relative") else f"{r['min_delta']:g}")
            for r in map(json.loads, sorted(rules)))
            + "; the weights kept are the last epoch's; train.epochs is the maximum.")
    else:
        parts.append("No stopping rule: every network trained train.epochs epochs (train.early_stopping is off).")
    for f in training.get("figures", []):
        parts.append(f"\n![training curves]({f})")
    if training.get("figure_error"):
        parts.append(f"\n(figure skipped: {training['figure_error']})")
    return "\n".join(parts)
