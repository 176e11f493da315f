"""``fwk report RUN_DIR...``: rebuild one run's report from its metrics.json, or combine several
runs into one comparison table and L1/DAME (and L1/FMPD) scatter plots with the Pareto front."""
from __future__ import annotations

import json
from pathlib import Path

from ..cache import atomic_write_bytes
from ..errors import FwkError
from ..runs import write_json
from .report import standard_scatters, write_report


def _load(run: Path) -> dict:
    p = run / "metrics.json"
    if not p.exists():
        raise FwkError(f"{run}: no metrics.json (not a finished run directory)")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise FwkError(f"{p}: unreadable ({exc})") from None


class _Dir:
    """The small part of RunContext that write_report needs, for an existing folder."""

    def __init__(self, run_dir: Path):
        self.run_dir = run_dir

    def path(self, *parts):
        p = self.run_dir.joinpath(*map(str, parts))
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_json(self, rel, obj):
        write_json(self.path(rel), obj)

    def write_text(self, rel, text):
        atomic_write_bytes(self.path(rel), text.encode())
        return self.path(rel)


def combine(runs: list[Path], out: Path) -> Path:
    """One comparison report in ``out`` of the models of several runs (labelled ``run:model``)."""
    merged = {"models": {}, "runs": {}}
    groups = {}
    for r in runs:
        m = _load(r)
        for label, per in m.get("models", {}).items():
            key = label if len(runs) == 1 else f"{r.name}:{label}"
            merged["models"][key] = per
            groups[key] = r.name
        merged["runs"][r.name] = str(r)
        merged.setdefault("dataset", m.get("dataset", {}))
    ctx = _Dir(out)
    figures = standard_scatters(ctx, merged, "test", groups=groups if len(runs) > 1 else None)
    title = "Comparison of " + ", ".join(r.name for r in runs)
    return write_report(ctx, title, merged, figures, notes=[f"runs: {', '.join(map(str, runs))}"])


def add_report_parser(sub):
    p = sub.add_parser("report", help="rebuild a run's report, or combine several runs into one comparison")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR")
    p.add_argument("--out", help="where the combined report goes (default: the run itself, or ./report-combined)")
    return p


def run_report(args) -> int:
    runs = [Path(r) for r in args.runs]
    for r in runs:
        if not r.is_dir():
            raise FwkError(f"{r}: not a folder")
    out = Path(args.out) if args.out else (runs[0] if len(runs) == 1 else Path("report-combined"))
    if len(runs) == 1 and not args.out:
        m = _load(runs[0])
        figs = m.get("figures", {})
        write_report(_Dir(runs[0]), f"Report: {runs[0].name}", {k: v for k, v in m.items() if k not in ("figures", "notes")},
                     {k: v for k, v in figs.items()}, notes=m.get("notes", []))
        print(runs[0] / "report.md")
        return 0
    print(combine(runs, out))
    return 0
