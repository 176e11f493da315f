"""Task ``grid``: run many configurations and compare them in one table (thesis 3.3.7, tables
3.3-3.5, figure 3.3).

Members are either recipe files (``recipes: [a.yaml, b.yaml]``, relative to the grid recipe) or
inline configurations merged onto a ``base`` recipe (``configs: {name: {key: value, ...}}``,
mappings merged key by key as ``extends:`` does). Each member runs as a sub-run in
``<run>/<name>/`` with its own recipe, split, statistics, checkpoints and report; a member whose
``metrics.json`` exists is finished and is not run again, so a killed grid resumes where it
stopped (``fwk run --resume``). The grid's report has one row per configuration and model with
L1, L2, DAME and FMPD on train and test (``columns``), and the L1/DAME and L1/FMPD scatters
with their Pareto fronts.

``executor`` says where the members run (``fwk_grid.executors``): ``local`` (default: in this
process, side by side in forked processes with the run's threads shared when ``train.side_by_side``
allows, as a run's models are, ``fwk.sidebyside``) or ``ray`` (Ray tasks declaring ``cpus`` / ``gpus`` each, on a local
Ray instance or the cluster at ``address``: ``fwk run grid.yaml executor=ray
executor.address=ray://head:10001``). Either way each member writes its own sub-run, so a grid
is resumable whichever executor ran it, and its report is the same. A member that fails is
logged with its error, gets a ``FAILED`` file in its sub-run, and is listed in the report; the
others go on; the grid then ends with an error (exit 2, the run marked ``FAILED``), and
``fwk run --resume`` reruns only the members without ``metrics.json``.

The grid recipe's own ``seed``, ``seeds`` and ``train`` apply to every member, over what the
member's recipe says: ``fwk run grid.yaml train.epochs=3`` trains every member 3 epochs (a quick
timing or smoke run of a whole study), ``seed: 1`` in the grid reruns the study with another seed.

**Seeds.** A member with ``seeds: [0, 1, 2]`` (its own, or the grid's: ``fwk run grid.yaml
--seeds 3``) fans out like members: each seed is a job of its own on the executor (``local`` or
``ray``), in ``<run>/<member>/seed-<s>/``, on the member's one split (``fwk.seeds``); when all
its seeds have finished, ``<run>/<member>/metrics.json`` and ``report.md`` combine them (mean ±
sd over seeds, ``fwk.evaluation.seeds``) and the grid's table shows mean ± sd. A seed whose
sub-run holds ``metrics.json`` is not run again.

``sweep: models.dsm.k`` (a dotted key of the members' recipes, numeric in each) names the value a
study varies: the report then also plots every metric against it, one line per split (the k
study of thesis figure 4.11).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import yaml

from fwk.cache import atomic_write_bytes
from fwk.errors import FwkError, RecipeError
from fwk.evaluation import display, markdown_table, standard_scatters, write_report
from fwk.evaluation.plots import line_plot
from fwk.evaluation.presentation import axis_unit
from fwk.evaluation.seeds import SEED_DIR, mean_sd
from fwk.hookspecs import hookimpl
from fwk.recipes import Kind, Spec, deep_merge, load_recipe, resolve
from fwk.seeds import member_seeds, plain_recipe, seed_finished, split_seed, write_seeds_report

from .executors import FAILED, Executor, member_job, run_local, run_ray

SHARED = ("seed", "seeds", "train")  # keys of the grid recipe that apply to every member


class Grid:
    """Run a list of recipes (or configurations of one base recipe) and compare them.

    ``columns``: the metrics of the combined table and sweep plots (default: the thesis's L1,
    L2, DAME and FMPD of tables 3.3-3.5). ``executor``: ``local``, ``ray``, or a mapping
    ``{name, address, cpus, gpus, num_cpus, num_gpus}`` (``fwk_grid.executors.Executor``)."""

    name = "grid"
    fans_out_seeds = True  # a grid's `seeds:` go to its members, each seed a job (fwk.runs.run_task)

    def __init__(self, recipes: list[str] | None = None, base: str | None = None,
                 configs: dict[str, dict] | None = None, splits: list[str] | None = None,
                 sweep: str | None = None,
                 columns: Annotated[list[Spec], Kind("metric")] = ("l1", "l2", "dame", "fmpd"),
                 executor: str | dict | None = "local"):
        if not recipes and not configs:
            raise RecipeError("recipes: a grid needs `recipes` or `base` with `configs`")
        if configs and not base:
            raise RecipeError("base: `configs` are merged onto a `base` recipe; give its path")
        self.recipes, self.base, self.configs = recipes or [], base, configs or {}
        self.splits = splits or ["train", "test"]
        self.sweep = sweep
        # a recipe's columns arrive as Specs, the default as names
        self.columns = [c.name if isinstance(c, Spec) else c for c in columns]
        self.executor = Executor.from_recipe(executor)

    def sweep_values(self, members: dict[str, dict]) -> dict[str, float]:
        """The value of ``sweep`` in each member's recipe (a RecipeError naming the member if absent)."""
        out = {}
        for name, data in members.items():
            v = data
            for part in self.sweep.split("."):
                if not isinstance(v, dict) or part not in v:
                    raise RecipeError(f"sweep: grid member {name} has no key {self.sweep!r}")
                v = v[part]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise RecipeError(f"sweep: {self.sweep} of grid member {name} is {v!r}, not a number")
            out[name] = float(v)
        return out

    def members(self, ctx) -> dict[str, dict]:
        """{member name: its recipe}: the recipe files, then the configurations merged on ``base``;
        the grid recipe's own ``seed`` and ``train`` (given in it or as ``train.epochs=3`` on the
        command line) merged onto every member last, so they win."""
        here = Path(ctx.source).parent if ctx.source else Path.cwd()
        shared = {k: (ctx.recipe or {})[k] for k in SHARED if k in (ctx.recipe or {})}
        out = {}
        for r in self.recipes:
            p = (here / r).resolve()
            out[p.stem] = load_recipe(p)
        if self.configs:
            base = load_recipe((here / self.base).resolve())
            for name, cfg in self.configs.items():
                d = deep_merge(base, cfg or {})
                d["name"] = name
                out[name] = d
        return {name: deep_merge(d, shared) for name, d in out.items()}

    def run(self, ctx):
        """Validate every member, run the unfinished ones as sub-runs, then combine their reports."""
        members = self.members(ctx)
        xs = self.sweep_values(members) if self.sweep else None
        resolved = {}
        for name, data in members.items():  # validate every member before running any
            try:
                resolved[name] = resolve(data, ctx.registry)
            except RecipeError as exc:
                raise RecipeError(f"grid member {name}: {exc}") from None
        jobs, seeded = [], {}
        for name, r in resolved.items():
            sub = ctx.run_dir / name
            if (sub / "metrics.json").exists():
                ctx.log(f"{name}: finished before, not run again")
                continue
            sub.mkdir(parents=True, exist_ok=True)
            plain = {k: v for k, v in r.data.items() if k != "_source"}
            atomic_write_bytes(sub / "recipe.yaml", yaml.safe_dump(plain, sort_keys=False).encode())
            if r.seeds is None:
                jobs.append(member_job(name, sub, r, ctx))
                continue
            seeded[name] = r
            for s, data in member_seeds(r).items():  # each seed a job, like a member (fwk.seeds)
                ssub = sub / SEED_DIR.format(s)
                if seed_finished(ssub):
                    ctx.log(f"{name} seed {s}: finished before, not run again")
                    continue
                ssub.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(ssub / "recipe.yaml", yaml.safe_dump(plain_recipe(data), sort_keys=False).encode())
                jobs.append(member_job(f"{name}/{ssub.name}", ssub, resolve(data, ctx.registry), ctx))
        if jobs and self.executor.name == "ray":
            outcomes = run_ray(jobs, self.executor, ctx.log)
        elif jobs:
            from fwk.forked import plan

            # a member's thread count from the run's and the grid's jobs, finished ones included
            how = plan(ctx, sum(len(r.seeds) if r.seeds is not None else 1 for r in resolved.values()))
            outcomes = run_local(jobs, ctx.log, ctx.registry,
                                 side_by_side=None if how is None else (*how, ctx.log_file))
        else:
            outcomes = {}
        failed = {}
        for n, o in outcomes.items():  # a seed's failure is its member's (the first one named)
            if not o["ok"]:
                member, _, seed = n.partition("/")
                failed.setdefault(member, (f"{seed}: " if seed else "") + o["error"])
        for name, r in seeded.items():  # a member's seeds combined once every one has finished
            if name not in failed:
                try:
                    write_seeds_report(ctx.child(name), r.seeds, split_seed(r.data),
                                       title=f"{name}: {len(r.seeds)} seed{'s' if len(r.seeds) != 1 else ''}",
                                       registry=ctx.registry)
                except FwkError as exc:
                    failed[name] = str(exc)
        for name in resolved:  # a member that failed without a word (a killed worker) is failed too
            if name not in failed and not (ctx.run_dir / name / "metrics.json").exists():
                failed[name] = "wrote no metrics.json" + (
                    " (on Ray across machines the runs folder must be shared: docs/scaling.md)"
                    if self.executor.name == "ray" and self.executor.address else "")
        results = {"models": {}, "members": list(resolved)}
        if failed:
            results["failed"] = failed
        for name in resolved:
            if name in failed:
                continue
            m = json.loads((ctx.run_dir / name / "metrics.json").read_text())
            for label, per in m.get("models", {}).items():
                key = name if len(m["models"]) == 1 else f"{name}/{label}"
                results["models"][key] = per
            results.setdefault("dataset", m.get("dataset", {}))
        shown = {m: display(m, ctx.registry) for m in self.columns}
        cols = ["configuration"] + [f"{m}{shown[m].suffix} {s}" for s in self.splits for m in self.columns]
        rows = [[key] + [mean_sd(per.get(s, {}).get(m), shown[m].scale) for s in self.splits for m in self.columns]
                for key, per in results["models"].items()]
        figures = standard_scatters(ctx, results, "test", registry=ctx.registry) if results["models"] else {}
        if xs:
            f = self._sweep_figures(ctx, results, xs)
            figures.update(f)
        sections = [("All configurations", markdown_table(rows, cols))]
        if failed:
            sections.append(("Failed members", markdown_table(
                [[n, e.replace("|", "/")] for n, e in failed.items()], ["member", "error"])
                + f"\n\nEach failed member's sub-run holds a `{FAILED}` file with the error; "
                  "`fwk run --resume` reruns only the members without `metrics.json`."))
        write_report(ctx, f"Grid: {ctx.recipe.get('name', self.name)} ({len(rows)} configurations)", results, figures,
                     sections=sections, registry=ctx.registry)
        if failed:  # after the report: the run is marked FAILED (kept where a member trained) and exits 2
            first = next(iter(failed))
            raise FwkError(f"grid: {len(failed)} of {len(resolved)} members failed ({first}: {failed[first]}"
                           f"{'; see the report' if len(failed) > 1 else ''}); the others finished; "
                           f"fwk run --resume reruns only the failed ones")

    def _sweep_figures(self, ctx, results: dict, xs: dict[str, float]) -> dict:
        """Each metric against the swept value, one line per split and model (figure 4.11)."""
        key = self.sweep.rsplit(".", 1)[-1]
        figures = {}
        for m in self.columns:
            shown = display(m, ctx.registry)
            summaries = [per.get(s, {}).get(m) for per in results["models"].values() for s in self.splits]
            summaries = [x for x in summaries if isinstance(x, dict) and x.get("mean") is not None]
            # in the dataset's units where every member has them (L1 in cm), else in the evaluation space
            inp = bool(summaries) and all(x.get("mean_input") is not None for x in summaries)
            series = {}
            for label, per in results["models"].items():
                member, _, model = label.partition("/")
                for s in self.splits:
                    x = per.get(s, {}).get(m, {})
                    v = x.get("mean_input" if inp else "mean")
                    if v is not None and member in xs:
                        name = f"{s}" + (f" {model}" if model else "")
                        series.setdefault(name, []).append((xs[member], v if inp else v / shown.scale))
            if not series:
                continue
            series = {n: tuple(map(list, zip(*sorted(p)))) for n, p in series.items()}
            units = next((x.get("units_input" if inp else "units", "") for x in summaries), "")
            unit = axis_unit(units, inp) + ("" if inp else shown.suffix)
            path = line_plot(series, ctx.path("figures", f"sweep_{key}_{m}.png"), f"{key} ({self.sweep}, log scale)",
                             f"{shown.label} ({unit})", title=f"{shown.label} against {key}", logx=True)
            figures[f"{m.upper()} against {key} (figure 4.11)"] = path
        return figures


@hookimpl
def fwk_register_tasks():
    return [Grid]
