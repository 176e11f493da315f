"""Seeds: one recipe trained once per seed, in one run directory, on one split.

``seeds: [0, 1, 2]`` in a recipe (or ``seeds: 3``: seeds 0, 1, 2; or ``fwk run R --seeds 3``)
runs the recipe's task once per seed, each time in a sub-run ``<run>/seed-<s>/``::

    <run>/recipe.yaml, versions.json, log.txt     the recipe as given (with seeds:), one log
    <run>/split.json                              the one split every seed trains on
    <run>/seed-<s>/                               a complete run of the member recipe of seed s:
        recipe.yaml                               the recipe with seed: s, split.seed fixed, no seeds:
        split.json stats/ models/ checkpoints/ curves/ tb/ figures/ metrics.json report.md
        scores.json                               per-subject test scores behind every mean
    <run>/metrics.json, report.md                 the seeds combined: mean ± sd, comparisons tested
                                                  (fwk.evaluation.seeds)

**The split is fixed.** The split's seed is the recipe's ``split.seed`` where it gives one, else
its ``seed:`` (default 0). A seed s of ``seeds:`` drives everything else ``seed:`` drives:
networks' initialisation, batching, sampling noise (``RunContext.seed``). The member recipe of
seed s is the recipe with ``seed: s``, ``split.seed`` set to the split's seed (for tasks that
take a ``split``) and no ``seeds:``; a seed's sub-run is an ordinary run of it, so

* ``seeds: [s]`` gives exactly the per-seed numbers of seed s in a run of ``seeds: [0, 1, 2]``
  (for a fixed thread count, as any rerun: docs/recipes.md, Threads);
* with ``seed: s`` and no ``split.seed``, seed s of ``seeds:`` is the plain run of ``seed: s``;
* ``fwk run <run>/seed-<s>/recipe.yaml`` reruns one seed alone, and ``fwk apply`` /
  ``fwk sample`` use a seed's sub-run (``<run>/seed-<s>``), which holds the models: given ``<run>``,
  the first seed's, or ``--seed-run S`` (``fwk.lifecycle.seed_sub_run``).

The seeds run side by side, each in a process forked from the run's, when the run has T >= 2
threads (``seed_rounds``: rounds of min(T, seeds) seeds, T // k threads each for a round of k;
``train.side_by_side: false``, a GPU, DDP or another system than Linux: one after another in
this process, as ``fwk.forked.plan`` rules for models). The dataset's cache (``fwk.cache``)
serves every seed after the first; the split and preprocessing are recomputed per seed,
identically, in well under a second. A seed whose sub-run holds ``metrics.json`` is finished: ``fwk run
--resume`` reruns only the others, each resumed from its checkpoints. Every model is trained
once per seed, the closed-form ones (``pca``, ``dt``) too: their numbers are the same on every
seed (sd 0), which shows the split did not move. A grid (``fwk_grid``) fans its members' seeds
out as jobs of their own (``member_seeds``), on its executor.
"""
from __future__ import annotations

import copy
import inspect
import json
import traceback
from pathlib import Path

import yaml

from .cache import atomic_write_bytes
from .errors import FwkError
from .evaluation.report import standard_scatters, write_report
from .evaluation.seeds import SEED_DIR, seed_runs, seeds_results
from .forked import SEEDS_ONE_AFTER_ANOTHER, plan, run_or_raise
from .recipes import resolve

#: the file a seed's sub-run holds while it failed (the run-state file of fwk.runs)
FAILED = "FAILED"


def split_seed(data: dict) -> int:
    """The seed of the split every seed of a recipe trains on: ``split.seed``, else ``seed``."""
    split = data.get("split")
    if isinstance(split, dict) and split.get("seed") is not None:
        return int(split["seed"])
    return int(data.get("seed", 0) or 0)


def fans_out_seeds(task_cls) -> bool:
    """Whether a task runs a recipe's ``seeds`` itself (its class says ``fans_out_seeds = True``:
    the grid, whose members each get the seeds) instead of fwk running it once per seed."""
    return bool(getattr(task_cls, "fans_out_seeds", False))


def takes_split(task_cls) -> bool:
    """Whether a task's recipe has a ``split`` key."""
    return "split" in inspect.signature(task_cls.__init__).parameters  # justified: the constructor is the recipe schema


def member_recipe(data: dict, seed: int, with_split: bool = True) -> dict:
    """The recipe of one seed: ``data`` with ``seed: seed``, no ``seeds`` and, ``with_split``,
    ``split.seed`` fixed to the split's seed (``split_seed``)."""
    out = copy.deepcopy({k: v for k, v in data.items() if k != "seeds"})
    if with_split:
        split = out.get("split")
        split = dict(split) if isinstance(split, dict) else {}
        split["seed"] = split_seed(data)
        out["split"] = split
    out["seed"] = int(seed)
    return out


def member_seeds(resolved) -> dict[int, dict]:
    """{seed: member recipe} of a resolved recipe with ``seeds`` (its ``_source`` kept, for
    paths relative to the recipe file)."""
    data = {k: v for k, v in resolved.data.items() if k != "_source"}
    with_split = takes_split(resolved.task.cls)
    out = {}
    for s in resolved.seeds or []:
        m = member_recipe(data, s, with_split)
        if resolved.source:
            m["_source"] = resolved.source
        out[int(s)] = m
    return out


def plain_recipe(data: dict) -> dict:
    """A member recipe as its sub-run's ``recipe.yaml`` holds it (``source``: the recipe file)."""
    out = {k: v for k, v in data.items() if k != "_source"}
    if data.get("_source"):
        out["source"] = data["_source"]
    return out


def seed_finished(sub: Path) -> bool:
    """Whether a seed's sub-run is finished: its ``metrics.json`` written, no ``FAILED``."""
    return (sub / "metrics.json").exists() and not (sub / FAILED).exists()


def seed_rounds(ctx, seeds: list) -> tuple[list[tuple[list, int]], int] | None:
    """([(the seeds of a round, each one's threads)], the run's threads T) when the run's seeds
    run side by side, else None (one after another, each with the run's T threads).

    With ``fwk.forked.plan``'s w = min(T, number of seeds) workers, the seeds are cut in the
    recipe's order into rounds of w; a round of k seeds runs them in k forked processes with
    T // k threads each (a round of one runs in the run's process). Which round a seed is in, and
    so its thread count, depends on T and the recipe only, also on a resume with fewer seeds left:
    a run's numbers depend on T and the recipe only. At T = 2 every model trains with one thread
    either way (seeds side by side: one after another in each seed's process; a lone seed: its
    models side by side), so the models are the ones seeds one after another fit, bit for bit;
    what changes is the wall time (a seed's long model no longer leaves the second core idle while
    it trains alone) and the thread count of each seed's predictions and metrics."""
    p = None if SEEDS_ONE_AFTER_ANOTHER[0] else plan(ctx, len(seeds))
    if p is None:
        return None
    w, _, T = p
    return [(seeds[i:i + w], T // len(seeds[i:i + w])) for i in range(0, len(seeds), w)], T


def run_seeds(resolved, ctx) -> None:
    """``fwk run`` of a recipe with ``seeds``: each seed's member recipe in its sub-run (finished
    ones skipped), side by side where ``seed_rounds`` says so, else one after another; then the
    run's combined metrics.json and report.md."""
    members = member_seeds(resolved)
    ctx.log(f"seeds {', '.join(map(str, members))} on the split of seed {split_seed(resolved.data)}")
    order = list(members)

    def one(s):
        sub = ctx.run_dir / SEED_DIR.format(s)
        data = members[s]
        member = resolve(data, ctx.registry)
        sub_ctx = ctx.child(sub.name)
        sub_ctx.seed, sub_ctx.recipe, sub_ctx.train = member.seed, member.data, member.train
        sub_ctx.source = member.source
        atomic_write_bytes(sub / "recipe.yaml", yaml.safe_dump(plain_recipe(data), sort_keys=False).encode())
        ctx.log(f"[seed {s}: {order.index(s) + 1}/{len(members)}] {sub}")
        try:
            member.task.build().run(sub_ctx)
        except BaseException as exc:
            try:
                atomic_write_bytes(sub / FAILED, (f"{type(exc).__name__}: {exc}\n\n{traceback.format_exc()}").encode())
            except OSError:
                pass
            raise
        (sub / FAILED).unlink(missing_ok=True)

    def todo(seeds):
        left = []
        for s in seeds:
            if seed_finished(ctx.run_dir / SEED_DIR.format(s)):
                ctx.log(f"seed {s}: finished before, not run again")
            else:
                left.append(s)
        return left

    how = seed_rounds(ctx, order)
    if how is None:
        for s in todo(order):
            one(s)
    else:
        rounds, T = how
        ctx.log(f"seeds side by side: {len(rounds[0][0])} at a time, each with {rounds[0][1]} of the run's {T} "
                f"threads" + (f" (the last {len(rounds[-1][0])} with {rounds[-1][1]})" if rounds[-1][1] != rounds[0][1]
                              else "") + "; train.side_by_side: false runs them one after another")
        for seeds, threads in rounds:
            left = todo(seeds)
            if len(seeds) == 1:  # a round of one: in this process, with the run's threads
                for s in left:
                    one(s)
            elif left:
                _forked_seeds(ctx, left, len(seeds), threads, T, one)
    write_seeds_report(ctx, order, split_seed(resolved.data), registry=ctx.registry)


def _forked_seeds(ctx, seeds, workers, threads, T, one) -> None:
    """Run ``one(s)`` for each seed in forked processes, ``workers`` at a time with ``threads``
    threads each; the first failure is raised once the running ones end (``fwk run --resume``
    runs what is left)."""
    why = (f"{workers} seeds side by side on the run's {T} threads, {threads} each; "
           "train.side_by_side: false runs them one after another")
    jobs = {f"seed {s}": (lambda s=s: one(s)) for s in seeds}
    run_or_raise(jobs, ctx, workers, threads, why, "seed", prefixes={name: f"[{name}] " for name in jobs},
                 what="{label}", doing="", one_at_a_time="runs one seed at a time")


def write_seeds_report(ctx, seeds, split_seed: int | None = None, title: str | None = None, registry=None) -> Path:
    """The run's ``metrics.json`` and ``report.md`` from its seeds' sub-runs
    (``fwk.evaluation.seeds.seeds_results``), and its ``split.json`` (the seeds' one split)."""
    runs = seed_runs(ctx.run_dir, seeds)
    missing = [s for s, p in runs.items() if not (p / "metrics.json").exists()]
    if missing:
        raise FwkError(f"{ctx.run_dir}: seed{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))} "
                       f"wrote no metrics.json")
    first = runs[int(seeds[0])]
    if (first / "split.json").exists():
        atomic_write_bytes(ctx.path("split.json"), (first / "split.json").read_bytes())
    results = seeds_results(ctx.run_dir, seeds, split_seed)
    figures = standard_scatters(ctx, results, "test", registry=registry) if results.get("models") else {}
    try:
        notes = json.loads((first / "metrics.json").read_text()).get("notes", [])
    except (OSError, ValueError):
        notes = []
    notes = [n for n in notes if not n.startswith("`fwk apply")]
    notes.append(f"`fwk apply` and `fwk sample` use one seed's models: of `{ctx.run_dir}`, the first seed's "
                 f"(`{first}`); `--seed-run S` or `{ctx.run_dir}/seed-S` picks another")
    name = (getattr(ctx, "recipe", None) or {}).get("name") or Path(ctx.run_dir).name
    title = title or f"{name}: {len(seeds)} seed{'s' if len(seeds) != 1 else ''}"
    return write_report(ctx, title, results, figures, notes=notes, registry=registry)
