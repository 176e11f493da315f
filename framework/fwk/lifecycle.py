"""One model life cycle for every task and command.

Inside a run (tasks)::

    model = build_model(spec, label, family, ctx)           # build, check the family
    fit_s = fit_or_resume(model, label, data, ctx)          # resume a finished model, or fit and save
    seconds = fit_models(models, data, ctx)                  # all of a run's models: side by side where faster

Reopening a finished run (``fwk apply``, ``fwk sample``, the ``edit``/``interpolate`` tasks)::

    run = open_run(run_dir, seed_run=None)                   # recipe, context, preprocessing, models' specs
    label = choose_model(run.specs, role, label, prefer)     # by --model LABEL, else by role
    model = run.model(label)                                 # built and loaded with the run's context

A model's state lives in ``<run>/models/<label>.safetensors`` (``fwk.safeio.save_state`` of
``model.state_dict()``: tensors, arrays and plain data, never a pickle); checkpoints of its
training under ``checkpoints/<label>/`` (the engine's, in the same format). ``load_state_dict``
always receives the run's context (``ctx``), which lends the cache to graph hierarchies. A run
of an earlier version (pickled ``models/<label>.pt``) is refused with the command that converts it
(``fwk convert RUN --trust``); a damaged, swapped or malformed run file is refused in one line
naming it.

A run of a recipe with ``seeds:`` keeps its models in one sub-run per seed (``seed-<s>/``,
``fwk.seeds``): ``open_run`` (through ``seed_sub_run``) opens one seed's sub-run, ``seed_run`` when
given (``--seed-run S``), else the first seed of ``seeds:``, and says which in one line. A seed's
sub-run, chosen so or given as ``RUN/seed-S``, must be finished (its ``metrics.json`` written, no
``FAILED``) and hold the member recipe of the run's ``recipe.yaml`` (itself checked against the
SHA-256 recorded when the run started); the run itself may still be running or have failed on
another seed. Every ``recipe.yaml`` is read with ``fwk.recipes.read_recipe_file`` (a key given
twice, an alias bomb: one line naming the file).
"""
from __future__ import annotations

import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from .data.preprocess import Preprocessor
from .errors import DataError, FwkError, RecipeError
from .protocols import FAMILIES, ChecksData, Model
from .recipes import Spec, parse_seeds, read_recipe_file, resolve
from .registry import Registry
from .runs import RunContext, check_recipe_hash, require_complete
from .safeio import LEGACY_SUFFIX, NARROWED, SUFFIX, legacy_error, load_json, load_npz, load_state, save_state, widen
from .seeds import FAILED, SEED_DIR, fans_out_seeds, member_recipe, plain_recipe, seed_finished, takes_split


def state_path(run_dir: Path, label: str) -> Path:
    """``<run_dir>/models/<label>.safetensors``: where a model's state is saved."""
    return Path(run_dir) / "models" / f"{label}{SUFFIX}"


def legacy_state_path(run_dir: Path, label: str) -> Path:
    """``<run_dir>/models/<label>.pt``: where earlier versions pickled a model's state."""
    return Path(run_dir) / "models" / f"{label}{LEGACY_SUFFIX}"


def has_state(run_dir: Path, label: str) -> bool:
    """Whether the run holds a saved state of ``label``; a pickled one of an earlier version
    (and none in the safe format) is refused with the command that converts it."""
    if state_path(run_dir, label).exists():
        return True
    if legacy_state_path(run_dir, label).exists():
        raise legacy_error(legacy_state_path(run_dir, label))
    return False


def build_model(spec: Spec, label: str, family: str, ctx: RunContext):
    """The model of ``models.<label>``, checked to be a model of ``family``."""
    try:
        model = spec.build() if isinstance(spec, Spec) else ctx.build("model", spec)
    except RecipeError as exc:  # a constructor's check names its parameter: add the recipe key
        msg = str(exc)
        raise RecipeError(msg if msg.startswith("models.") else f"models.{label}.{msg}") from None
    if not isinstance(model, Model) or model.task_family not in FAMILIES:
        raise RecipeError(f"models.{label}: {spec.name} does not play the model role "
                          f"(fit, state_dict, load_state_dict, task_family; see fwk.protocols.Model)")
    if model.task_family != family:
        raise RecipeError(f"models.{label}: {model.name} is a {model.task_family} model, not a {family} model")
    return model


def build_models(specs: dict, family: str, ctx: RunContext, data) -> dict:
    """Every model of ``models:`` built and checked against ``data`` (``ChecksData``) before
    any of them trains, so that an impossible recipe value fails in one line without minutes
    of training lost first. Errors name the recipe key (``models.<label>.``)."""
    models = {label: build_model(spec, label, family, ctx) for label, spec in specs.items()}
    for label, model in models.items():
        if isinstance(model, ChecksData):
            try:
                model.check_data(data)
            except RecipeError as exc:
                msg = str(exc)
                raise RecipeError(msg if msg.startswith("models.") else f"models.{label}.{msg}") from None
    return models


def _model_id(model) -> str:
    cls = type(model)
    return f"{cls.__module__}.{cls.__qualname__}"


def save_model_state(model, path: Path, label: str) -> Path:
    """``model.state_dict()`` saved to ``path`` in the safe format (``fwk.safeio``), with the
    model's registered name and label, which ``load_model_state`` checks (and its class, for
    whoever reads the file)."""
    return save_state(path, model.state_dict(), {"model": _model_id(model), "name": model.name, "label": label})


def load_model_state(model, path: Path, ctx: RunContext | None, label: str | None = None) -> None:
    """Load the state saved at ``path`` into ``model``: verified (``fwk.safeio.load_state``), of
    the model's name and label (a swapped file is refused) and accepted by its ``load_state_dict``; every
    failure is a ``DataError`` naming the file."""
    state, meta = load_state(path, with_meta=True)
    if meta.get(NARROWED):  # a packed model (fwk pack): stored narrow, computed with in fwk's types
        state = widen(state)
    saved = meta.get("name")  # the registered name: stable when a plugin moves its class
    if saved is not None and saved != model.name:
        raise DataError(f"{path}: holds the state of another model ({meta.get('label', '?')!s}: "
                        f"{saved!s}), not of {label or 'this model'} ({model.name})")
    if label is not None and meta.get("label") not in (None, label):
        raise DataError(f"{path}: holds the state of model {meta.get('label')!s}, not of {label}")
    try:
        model.load_state_dict(state, ctx=ctx)
    except DataError:
        raise
    except Exception as exc:  # a state of the same class with other shapes or keys (a changed recipe)
        msg = " ".join(str(exc).split())
        raise DataError(f"{path}: does not fit the model {model.name} the recipe builds "
                        f"({type(exc).__name__}: {msg[:160]})") from None


def fit_or_resume(model, label: str, data, ctx: RunContext) -> float:
    """Fit ``model`` on ``data`` (its checkpoints scoped to ``label``) and save it as
    ``models/<label>.safetensors``; with ``ctx.resume`` and that file present, load it instead.
    A ``RecipeError`` the model raises while fitting (a parameter the data refutes) is prefixed
    with ``models.<label>.``. Returns the seconds spent."""
    path = state_path(ctx.run_dir, label)
    t0 = time.perf_counter()
    if ctx.resume and has_state(ctx.run_dir, label):
        ctx.log(f"[{label}] loading the finished model from {path}")
        load_model_state(model, path, ctx, label)
    else:
        ctx.log(f"[{label}] fitting {model.name}")
        try:
            model.fit(data, ctx.scoped(label))
        except RecipeError as exc:  # a parameter the data refutes (too many components): name its key
            msg = str(exc)
            raise RecipeError(msg if msg.startswith("models.") else f"models.{label}.{msg}") from None
        save_model_state(model, ctx.path("models", f"{label}{SUFFIX}"), label)
    return time.perf_counter() - t0


def fit_models(models: dict, data, ctx: RunContext) -> dict[str, float]:
    """``fit_or_resume`` for every model of ``models`` (label -> model, the recipe's order):
    side by side in forked processes where one model cannot use the run's threads
    (``fwk.sidebyside``: CPU, two or more models, ``train.side_by_side``), else one after
    another. Returns label -> seconds spent fitting (or loading) it."""
    from . import forked, sidebyside

    seconds: dict[str, float] = {}
    how = forked.plan(ctx, len(models))
    todo = [lb for lb in models if not (ctx.resume and has_state(ctx.run_dir, lb))]
    if how is not None and todo:
        workers, threads, T = how  # todo holds no saved state, so fit_or_resume fits each
        seconds = sidebyside.fit_side_by_side(
            {lb: (lambda lb=lb: fit_or_resume(models[lb], lb, data, ctx)) for lb in todo}, ctx, workers, threads, T)
    for label, model in models.items():
        if label in seconds:
            load_model_state(model, state_path(ctx.run_dir, label), ctx, label)
        else:
            seconds[label] = fit_or_resume(model, label, data, ctx)
    return seconds


def choose_model(specs: dict, role, label: str | None = None, prefer=None, what: str = "--model",
                 source: str = "") -> str:
    """The label of the model to use: ``label`` when given (checked to play ``role``), else the
    first model playing ``prefer`` (a role, optional), else the first playing ``role``."""
    from .protocols import plays

    where = f" of {source}" if source else ""
    if label is not None:
        if label not in specs:
            raise FwkError(f"{what} {label}: not a model{where} (models: {', '.join(specs) or 'none'})")
        if not plays(specs[label].cls, role):
            raise FwkError(f"{what} {label}: {specs[label].name} does not play the {role.__name__} role")
        return label
    for r in ([prefer] if prefer is not None else []) + [role]:
        found = next((k for k, s in specs.items() if plays(s.cls, r)), None)
        if found is not None:
            return found
    raise FwkError(f"no model{where} plays the {role.__name__} role (models: {', '.join(specs) or 'none'})")


@dataclass
class OpenedRun:
    """A finished run reopened: its resolved recipe, a context writing into the same directory,
    the fitted preprocessing, and the specs of its models (label -> Spec)."""

    run_dir: Path
    resolved: object
    ctx: RunContext
    specs: dict
    metrics: dict = field(default_factory=dict)
    _pre: Preprocessor | None = None

    @property
    def task(self) -> str:
        return self.resolved.task.name

    @property
    def params(self) -> dict:
        return self.resolved.task.params

    @property
    def preprocessor(self) -> Preprocessor:
        if self._pre is None:
            path = self.run_dir / "stats" / "preprocess.npz"
            if not path.exists():
                raise FwkError(f"{path}: missing; is {self.run_dir} a finished run?")
            state = load_npz(path)
            try:
                self._pre = Preprocessor.from_state(state)
            except Exception as exc:  # an npz of other arrays (swapped, edited)
                raise DataError(f"{path}: not the preprocessing of a run ({type(exc).__name__}: "
                                f"{str(exc)[:120]})") from None
        return self._pre

    def model(self, label: str):
        """The trained model ``label``, built from its spec and loaded from
        ``models/<label>.safetensors``."""
        if label not in self.specs:
            raise FwkError(f"--model {label}: not a model of {self.run_dir} (models: {', '.join(self.specs)})")
        path = state_path(self.run_dir, label)
        if not has_state(self.run_dir, label):
            raise FwkError(f"{path}: missing; is {self.run_dir} a finished run?")
        m = self.specs[label].build()
        load_model_state(m, path, self.ctx, label)
        return m


def read_run_recipe(run_dir) -> dict:
    """A run's ``recipe.yaml`` as a mapping, read with every check of
    ``fwk.recipes.read_recipe_file`` (UTF-8, size, a key given twice, alias bombs): one line naming
    the file when it fails."""
    run_dir = Path(run_dir)
    if not (run_dir / "recipe.yaml").exists():
        raise FwkError(f"{run_dir}: not a run directory (no recipe.yaml)")
    return read_recipe_file(run_dir / "recipe.yaml", "run recipe")


_SEED_FOLDER = re.compile(r"seed-(\d+)")


def _run_seeds(run_dir: Path, data: dict, registry: Registry) -> list[int] | None:
    """The seeds of a run whose recipe has ``seeds:`` and whose task runs them as ``seed-<s>/``
    sub-runs (``fwk.seeds``); None for a run of one seed or a task fanning seeds out itself."""
    if data.get("seeds") is None:
        return None
    try:
        seeds = parse_seeds(data.get("seeds"))
        cls = registry.get("task", data.get("task"), key_path="task") if isinstance(data.get("task"), str) else None
    except RecipeError as exc:
        raise FwkError(f"{run_dir}/recipe.yaml no longer validates: {exc}") from None
    if cls is not None and fans_out_seeds(cls):  # a grid: <member>/seed-<s>/
        return None
    return seeds


def _check_seed(run_dir: Path, data: dict, seed: int, registry: Registry) -> Path:
    """``run_dir/seed-<seed>``, checked: finished, and holding the member recipe of ``data`` (the
    run's recipe, its SHA-256 checked first)."""
    sub = run_dir / SEED_DIR.format(seed)
    if not sub.is_dir():
        raise FwkError(f"{sub}: missing; seed {seed} of {run_dir} was not run (continue it with "
                       f"fwk run --resume {run_dir})")
    if not seed_finished(sub):
        if (sub / FAILED).exists():
            why = ((sub / FAILED).read_text(errors="replace").splitlines() or ["see FAILED"])[0]
            raise FwkError(f"{sub}: seed {seed} failed ({why[:160]}); continue it with fwk run --resume {run_dir}")
        raise FwkError(f"{sub}: seed {seed} did not finish (no metrics.json); continue it with "
                       f"fwk run --resume {run_dir}")
    check_recipe_hash(run_dir)  # the run's recipe.yaml as the run started: the seeds' recipes follow from it
    try:
        with_split = takes_split(registry.get("task", data.get("task"), key_path="task"))
    except RecipeError as exc:
        raise FwkError(f"{run_dir}/recipe.yaml no longer validates: {exc}") from None
    # `source` (the recipe file relative paths resolve from) aside: a grid member's recipe.yaml
    # leaves it out, its seeds' record it
    member = member_recipe({k: v for k, v in data.items() if k not in ("_source", "source")}, seed, with_split)
    got = {k: v for k, v in read_run_recipe(sub).items() if k != "source"}
    if got != plain_recipe(member):
        raise DataError(f"{sub / 'recipe.yaml'}: not the recipe of seed {seed} of {run_dir}/recipe.yaml "
                        f"(edited after the run)")
    return sub


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def seed_sub_run(run_dir, seed_run: int | None = None, registry: Registry | None = None, say=_say,
                 choose: str = "--seed-run S or {run}/seed-S") -> Path:
    """The folder to reopen for ``run_dir``: ``run_dir`` itself, or, for a run with ``seeds:``
    (``fwk.seeds``), one seed's sub-run: ``seed-<seed_run>/``, else the first seed of ``seeds:``,
    which ``say`` (stderr by default; None: silent) names in one line, with ``choose`` (how to pick
    another). A seed's sub-run must be finished and hold its member recipe (``_check_seed``), given
    as ``RUN/seed-S`` too; ``seed_run`` on a run of one seed, or not one of its seeds, is refused."""
    from .plugins import get_registry

    run_dir = Path(run_dir)
    data = read_run_recipe(run_dir)
    registry = registry or get_registry()
    seeds = _run_seeds(run_dir, data, registry)
    if seeds is None:
        m = _SEED_FOLDER.fullmatch(run_dir.name)
        parent = run_dir.parent
        if m and (parent / "recipe.yaml").exists():  # RUN/seed-S: a seed of a run with seeds:
            top = read_run_recipe(parent)
            top_seeds = _run_seeds(parent, top, registry)
            if top_seeds is not None and int(m.group(1)) in top_seeds:
                if seed_run is not None and seed_run != int(m.group(1)):
                    raise FwkError(f"--seed-run {seed_run}: {run_dir} is the sub-run of seed {m.group(1)}; "
                                   f"give {parent} --seed-run {seed_run}, or {parent / SEED_DIR.format(seed_run)}")
                return _check_seed(parent, top, int(m.group(1)), registry)
        if seed_run is not None:
            raise FwkError(f"--seed-run {seed_run}: {run_dir} is a run of one seed (its recipe has no seeds:)")
        return run_dir
    if seed_run is None:
        seed_run = seeds[0]
        if say is not None:
            hint = choose.format(run=run_dir)
            say(f"{run_dir} has seeds {', '.join(map(str, seeds))}: using {SEED_DIR.format(seed_run)} "
                f"(choose with {hint})")
    elif seed_run not in seeds:
        raise FwkError(f"--seed-run {seed_run}: not a seed of {run_dir} (its seeds: {', '.join(map(str, seeds))})")
    return _check_seed(run_dir, data, int(seed_run), registry)


def open_run(run_dir, registry: Registry | None = None, quiet: bool = True, task: str | None = None,
             seed_run: int | None = None, say=_say, choose: str = "--seed-run S or {run}/seed-S") -> OpenedRun:
    """Reopen a finished run directory (its ``recipe.yaml`` validated against today's registry);
    ``task`` (optional) is the task it must be a run of. A run that failed, was killed or is
    still running (``fwk.runs.run_state``) is refused with the command that continues it. A run
    with ``seeds:`` opens one seed's sub-run (``seed_sub_run``: ``seed_run``, else its first
    seed, said through ``say``)."""
    from .plugins import get_registry

    registry = registry or get_registry()
    run_dir = seed_sub_run(run_dir, seed_run, registry, say=say, choose=choose)
    require_complete(run_dir)  # a failed, killed or running run's files are not used
    check_recipe_hash(run_dir)  # recipe.yaml as the run was trained with, not edited since
    data = read_run_recipe(run_dir)
    try:
        resolved = resolve(data, registry)
    except RecipeError as exc:
        raise FwkError(f"{run_dir}/recipe.yaml no longer validates: {exc}") from None
    if task is not None and resolved.task.name != task:
        raise FwkError(f"{run_dir} is a {resolved.task.name} run, not a {task} run")
    ctx = RunContext(run_dir, registry, None, resolved.seed, recipe=data, train=resolved.train, quiet=quiet)
    ctx.source = resolved.source
    metrics = {}
    if (run_dir / "metrics.json").exists():
        metrics = load_json(run_dir / "metrics.json")
    specs = dict(resolved.task.params.get("models") or {})
    return OpenedRun(run_dir, resolved, ctx, specs, metrics)
