"""``fwk report RUN_DIR...``: rebuild one run's report from its metrics.json, or combine several
runs into one comparison table and L1/DAME (and L1/FMPD) scatter plots with the Pareto front.

Only complete runs are read (a failed, killed or running one is refused with the command that
continues it: ``fwk.runs.run_state``). Runs of different tasks, or on different datasets (the
recipe's ``dataset`` and ``split``), give numbers that do not compare: they are refused unless
``--mix`` is given, and then the report says what differs.
"""
from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path

from ..cache import atomic_write_bytes
from ..data.split import SplitConfig
from ..errors import FwkError, RecipeError
from ..plugins import get_registry
from ..recipes import read_recipe_file, to_plain
from ..paths import check_dir
from ..runs import require_complete, write_json
from .report import standard_scatters, write_report


def _load(run: Path) -> dict:
    p = run / "metrics.json"
    if not p.exists():
        raise FwkError(f"{run}: no metrics.json (not a finished run directory)")
    try:
        m = json.loads(p.read_bytes())
    except (ValueError, RecursionError) as exc:  # not JSON, not UTF-8
        raise FwkError(f"{p}: unreadable ({str(exc)[:160]})") from None
    if not isinstance(m, dict):
        raise FwkError(f"{p}: not the metrics of a run (a JSON {type(m).__name__}, not an object)")
    for key, kind in (("models", dict), ("figures", dict), ("notes", list), ("dataset", dict)):
        if key in m and not isinstance(m[key], kind):
            raise FwkError(f"{p}: not the metrics of a run ({key} is a {type(m[key]).__name__})")
    bad = [k for k, v in m.get("models", {}).items() if not isinstance(v, dict)]
    if bad:
        raise FwkError(f"{p}: not the metrics of a run (models.{bad[0]} is a {type(m['models'][bad[0]]).__name__})")
    return m


def _malformed(runs: list[Path], exc: Exception) -> FwkError:
    """What a report built from a metrics.json of the right outline but wrong contents (edited,
    another program's) says: one line naming the file(s)."""
    files = ", ".join(str(r / "metrics.json") for r in runs)
    return FwkError(f"{files}: not the metrics of a finished run ({type(exc).__name__}: {str(exc)[:120]})")


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


def _with_defaults(value):
    """A recipe's ``dataset`` as a mapping with every constructor default filled in, so that
    ``synthetic-heads`` and ``{name: synthetic-heads, n_vertices: 6000}`` compare equal; as it
    is when its dataset is not registered (a plugin since removed)."""
    if isinstance(value, str):
        value = {"name": value}
    if not isinstance(value, dict) or not isinstance(value.get("name"), str):
        return value
    try:
        cls = get_registry().get("dataset", value["name"])
    except FwkError:
        return value
    sig = inspect.signature(cls.__init__)  # justified: the constructor is the recipe schema (fwk.hookspecs)
    defaults = {n: p.default for n, p in sig.parameters.items()
                if n != "self" and p.default is not p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
    return {"name": value["name"], **to_plain(defaults), **{k: v for k, v in value.items() if k != "name"}}


def _split(value):
    """A recipe's ``split`` with its defaults (``fwk.data.split.SplitConfig``) filled in."""
    if value is None:
        return to_plain(SplitConfig())
    if not isinstance(value, dict) or not set(value) <= {f.name for f in dataclasses.fields(SplitConfig)}:
        return value  # not a split this fwk reads: compared as written
    try:
        return to_plain(SplitConfig(**value))
    except RecipeError:
        return value


def identity(run: Path) -> dict:
    """What must agree for two runs' numbers to compare: the task and the data (the recipe's
    ``dataset``, its defaults filled in, and ``split``; without a recipe, metrics.json's dataset
    name, size and units)."""
    recipe = {}
    if (run / "recipe.yaml").exists():
        try:  # every check of a recipe file: a key given twice, an alias bomb, not UTF-8 (one line)
            recipe = read_recipe_file(run / "recipe.yaml", "run recipe")
        except RecipeError as exc:
            raise FwkError(str(exc)) from None
    if not recipe:
        ds = _load(run).get("dataset", {})
        return {"task": None, "dataset": {k: ds[k] for k in ("name", "n_vertices", "units") if k in ds} or None,
                "split": None}
    return {"task": recipe.get("task"), "dataset": _with_defaults(recipe.get("dataset")),
            "split": _split(recipe.get("split"))}


def _describe(value) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_describe(v)}" for k, v in value.items()) + "}"
    return "none" if value is None else str(value)


def differences(runs: list[Path]) -> list[str]:
    """One line per key (task, dataset, split) on which the runs disagree, naming each run's
    value (of a mapping, only the entries that differ)."""
    ids = {r: identity(r) for r in runs}
    out = []
    for key in ("task", "dataset", "split"):
        values = [ids[r][key] for r in runs]
        if any(v != values[0] for v in values[1:]):
            if all(isinstance(v, dict) for v in values):
                keys = [k for k in dict.fromkeys(k for v in values for k in v)
                        if any(v.get(k) != values[0].get(k) for v in values)]
                values = [{k: v.get(k) for k in keys} for v in values]
            out.append(f"{key}: " + "; ".join(f"{r.name} {_describe(v)}" for r, v in zip(runs, values)))
    return out


def combine(runs: list[Path], out: Path, mix: bool = False) -> Path:
    """One comparison report in ``out`` of the models of several runs (labelled ``run:model``).
    Runs of different tasks or data are refused unless ``mix``."""
    diff = differences(runs)
    if diff and not mix:
        raise FwkError("these runs do not compare (" + " | ".join(diff) + "); "
                       "give --mix to put them in one table anyway")
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
    notes = [f"runs: {', '.join(map(str, runs))}"]
    if diff:
        notes.append("mixed with --mix: the runs differ in " + "; ".join(diff) +
                     ". Their numbers (and the Pareto front) do not compare like with like")
    return write_report(ctx, title, merged, figures, notes=notes)


def add_report_parser(sub):
    """The ``fwk report`` subcommand's parser."""
    p = sub.add_parser("report", help="rebuild a run's report, or combine several runs into one comparison")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR")
    p.add_argument("--out", help="where the combined report goes (default: the run itself, or ./report-combined)")
    p.add_argument("--mix", action="store_true",
                   help="combine runs of different tasks or datasets (refused otherwise: their numbers do not compare)")
    return p


def run_report(args) -> int:
    """``fwk report``: rebuild one run's report, or combine several (see the module docstring)."""
    runs = [Path(r) for r in args.runs]
    for r in runs:
        if not r.is_dir():
            raise FwkError(f"{r}: not a folder")
        require_complete(r)
    out = Path(args.out) if args.out else (runs[0] if len(runs) == 1 else Path("report-combined"))
    if out != runs[0] or len(runs) > 1:
        if (out / "recipe.yaml").exists():  # a combined report would replace the run's own numbers
            raise FwkError(f"--out {out}: a run directory (its metrics.json and report.md would be replaced "
                           f"by the comparison); give another folder")
        check_dir(out, "--out" if args.out else "the report folder")
    if len(runs) == 1 and not args.out:
        m = _load(runs[0])
        figs = m.get("figures", {})
        try:
            write_report(_Dir(runs[0]), f"Report: {runs[0].name}", {k: v for k, v in m.items() if k not in ("figures", "notes")},
                         {k: v for k, v in figs.items()}, notes=m.get("notes", []))
        except (KeyError, TypeError, AttributeError, ValueError, IndexError) as exc:  # contents tampered with
            raise _malformed(runs, exc) from exc
        print(runs[0] / "report.md")
        return 0
    try:
        print(combine(runs, out, mix=args.mix))
    except (KeyError, TypeError, AttributeError, ValueError, IndexError) as exc:
        raise _malformed(runs, exc) from exc
    return 0
