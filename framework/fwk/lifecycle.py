"""One model life cycle for every task and command.

Inside a run (tasks)::

    model = build_model(spec, label, family, ctx)           # build, check the family
    fit_s = fit_or_resume(model, label, data, ctx)          # resume a finished model, or fit and save

Reopening a finished run (``fwk apply``, ``fwk sample``, the ``edit``/``interpolate`` tasks)::

    run = open_run(run_dir)                                  # recipe, context, preprocessing, models' specs
    label = choose_model(run.specs, role, label, prefer)     # by --model LABEL, else by role
    model = run.model(label)                                 # built and loaded with the run's context

A model's state lives in ``<run>/models/<label>.pt`` (``torch.save(model.state_dict())``);
checkpoints of its training under ``checkpoints/<label>/`` (the engine's). ``load_state_dict``
always receives the run's context (``ctx``), which lends the cache to graph hierarchies.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .data.preprocess import Preprocessor
from .errors import FwkError, RecipeError
from .protocols import FAMILIES, ChecksData, Model
from .recipes import Spec, resolve
from .registry import Registry
from .runs import RunContext, require_complete


def state_path(run_dir: Path, label: str) -> Path:
    return Path(run_dir) / "models" / f"{label}.pt"


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


def load_model_state(model, path: Path, ctx: RunContext | None) -> None:
    import torch  # deferred: torch costs ~1 s of import time that `fwk list` / `fwk show` need not pay

    model.load_state_dict(torch.load(path, weights_only=False), ctx=ctx)


def fit_or_resume(model, label: str, data, ctx: RunContext) -> float:
    """Fit ``model`` on ``data`` (its checkpoints scoped to ``label``) and save it as
    ``models/<label>.pt``; with ``ctx.resume`` and that file present, load it instead.
    A ``RecipeError`` the model raises while fitting (a parameter the data refutes) is prefixed
    with ``models.<label>.``. Returns the seconds spent."""
    path = state_path(ctx.run_dir, label)
    t0 = time.perf_counter()
    if ctx.resume and path.exists():
        ctx.log(f"[{label}] loading the finished model from {path}")
        load_model_state(model, path, ctx)
    else:
        ctx.log(f"[{label}] fitting {model.name}")
        try:
            model.fit(data, ctx.scoped(label))
        except RecipeError as exc:  # a parameter the data refutes (too many components): name its key
            msg = str(exc)
            raise RecipeError(msg if msg.startswith("models.") else f"models.{label}.{msg}") from None
        ctx.save_torch(f"models/{label}.pt", model.state_dict())
    return time.perf_counter() - t0


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
            with np.load(path) as z:
                self._pre = Preprocessor.from_state({k: z[k] for k in z.files})
        return self._pre

    def model(self, label: str):
        """The trained model ``label``, built from its spec and loaded from ``models/<label>.pt``."""
        if label not in self.specs:
            raise FwkError(f"--model {label}: not a model of {self.run_dir} (models: {', '.join(self.specs)})")
        path = state_path(self.run_dir, label)
        if not path.exists():
            raise FwkError(f"{path}: missing; is {self.run_dir} a finished run?")
        m = self.specs[label].build()
        load_model_state(m, path, self.ctx)
        return m


def open_run(run_dir, registry: Registry | None = None, quiet: bool = True, task: str | None = None) -> OpenedRun:
    """Reopen a finished run directory (its ``recipe.yaml`` validated against today's registry);
    ``task`` (optional) is the task it must be a run of. A run that failed, was killed or is
    still running (``fwk.runs.run_state``) is refused with the command that continues it."""
    from .plugins import get_registry

    run_dir = Path(run_dir)
    if not (run_dir / "recipe.yaml").exists():
        raise FwkError(f"{run_dir}: not a run directory (no recipe.yaml)")
    require_complete(run_dir)  # a failed, killed or running run's files are not used
    registry = registry or get_registry()
    data = yaml.safe_load((run_dir / "recipe.yaml").read_text())
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
        metrics = json.loads((run_dir / "metrics.json").read_text())
    specs = dict(resolved.task.params.get("models") or {})
    return OpenedRun(run_dir, resolved, ctx, specs, metrics)
