"""Recipes: YAML (safe_load only), ``extends:``, ``a.b.c=value`` overrides, validation.

A recipe names a task and gives the task's parameters as top-level keys::

    task: reconstruct            # a registered task
    extends: base.yaml           # optional: inherit and override another recipe (path relative to this file)
    name: my-study               # optional: the run directory's name (default: the file's stem)
    seed: 0                      # one seed for sampling, splits, initialisation and batching
    seeds: [0, 1, 2]             # optional: train every model once per seed on the split of `seed` (fwk.runs)
    train: {epochs: 10}          # fwk.engine.TrainConfig
    dataset: {name: synthetic-heads, n_vertices: 1500}
    models: {pca: {name: pca, n_components: 32}}

Every section is validated against its class's constructor signature, recursively: a parameter
annotated ``Annotated[Spec, Kind("conv")]`` holds a registered component (a name, or a mapping
with ``name`` and that component's parameters); a dataclass-annotated parameter holds a mapping
of that dataclass's fields. Errors name the key path: ``model.conv.lenght: unknown parameter of
spiral; did you mean length?``. There are no dotted import paths: only registered components.
"""
from __future__ import annotations

import copy
import dataclasses
import inspect
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, get_args, get_origin

import yaml

from .data.template import check_units
from .engine.config import TrainConfig
from .errors import RecipeError
from .plugins import get_registry
from .registry import Registry, did_you_mean

RESERVED = ("task", "extends", "name", "seed", "seeds", "train", "description", "source")


class Kind:
    """Annotation marker: ``Annotated[Spec, Kind("representation")]``."""

    def __init__(self, kind: str):
        self.kind = kind

    def __repr__(self):
        return f"Kind({self.kind!r})"


@dataclass
class Spec:
    """A validated reference to a registered component and its parameters."""

    kind: str
    name: str
    params: dict = field(default_factory=dict)
    cls: type | None = None
    path: str = ""

    def build(self, *args, **extra):
        """The component: its class called with ``args`` and the recipe's parameters updated by
        ``extra``."""
        if self.cls is None:
            raise RuntimeError(f"{self.path}: spec of {self.kind} {self.name!r} is not resolved")
        return self.cls(*args, **{**self.params, **extra})

    def to_dict(self) -> dict:
        """The recipe form: ``{name: ..., parameters...}``."""
        return {"name": self.name, **{k: to_plain(v) for k, v in self.params.items()}}


def to_plain(v):
    """Specs and dataclasses back to plain YAML-able data."""
    if isinstance(v, Spec):
        return v.to_dict()
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: to_plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {k: to_plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_plain(x) for x in v]
    return v


# ----------------------------------------------------------------------------- loading

def _read_yaml(path: Path) -> dict:
    if not path.exists():
        raise RecipeError(f"recipe file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise RecipeError(f"{path}: a recipe must be a mapping of keys to values")
    return data


def deep_merge(base: dict, over: dict) -> dict:
    """``base`` updated by ``over``, recursively; a mapping that names another component replaces
    the old one instead of merging into it."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and "name" not in v:
            out[k] = deep_merge(out[k], v)
        elif isinstance(v, dict) and isinstance(out.get(k), dict) and v.get("name") == out[k].get("name"):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _load_with_extends(path: Path, seen: tuple = ()) -> dict:
    path = path.resolve()
    if path in seen:
        chain = " -> ".join(str(p.name) for p in (*seen, path))
        raise RecipeError(f"extends: recipes extend each other in a cycle ({chain})")
    data = _read_yaml(path)
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str):
        raise RecipeError(f"{path.name}: extends: expected a recipe path, got {parent!r}")
    base = _load_with_extends((path.parent / parent), (*seen, path))
    return deep_merge(base, data)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b.c=value`` -> (['a', 'b', 'c'], the value read as YAML)."""
    if "=" not in text:
        raise RecipeError(f"override {text!r}: expected key.path=value")
    key, _, raw = text.partition("=")
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise RecipeError(f"override {text!r}: expected key.path=value")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """A copy of ``data`` with each ``key.path=value`` override set (mappings created on the way)."""
    data = copy.deepcopy(data)
    for text in overrides or []:
        keys, value = parse_override(text)
        node = data
        for i, k in enumerate(keys[:-1]):
            nxt = node.get(k)
            if isinstance(nxt, str) and i < len(keys) - 1:  # `dataset: x` then `dataset.n=5`
                nxt = {"name": nxt}
            if not isinstance(nxt, dict):
                if nxt is not None:
                    raise RecipeError(f"override {text}: {'.'.join(keys[: i + 1])} is not a mapping")
                nxt = {}
            node[k] = nxt
            node = nxt
        node[keys[-1]] = value
    return data


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> dict:
    """Read a recipe file, resolve ``extends`` and apply ``key=value`` overrides (not validated)."""
    path = Path(path)
    data = _load_with_extends(path)
    data = apply_overrides(data, overrides or [])
    data.setdefault("name", path.stem)
    data["_source"] = str(path.resolve())  # where relative paths inside the recipe start
    return data


# ----------------------------------------------------------------------------- validation

def _type_name(tp) -> str:
    if tp is inspect.Parameter.empty or tp is Any:
        return "any value"
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin is not None:
        return getattr(origin, "__name__", str(origin))
    return getattr(tp, "__name__", str(tp))


def _hints(func) -> dict:
    try:
        return typing.get_type_hints(func, include_extras=True)
    except Exception:
        return {}


def validate_params(cls: type, params: dict, path: str, registry: Registry, label: str | None = None) -> dict:
    """Check ``params`` against ``cls``'s constructor and convert nested components."""
    if not isinstance(params, dict):
        raise RecipeError(f"{path}: expected a mapping of parameters, got {params!r}")
    label = label or getattr(cls, "name", cls.__name__)
    init = cls.__init__ if not dataclasses.is_dataclass(cls) else cls
    sig = inspect.signature(init)  # justified: the constructor is the recipe schema (fwk.hookspecs)
    hints = _hints(cls.__init__) if not dataclasses.is_dataclass(cls) else _hints(cls)
    supplied = set(getattr(cls, "build_args", ()))  # given by the framework at build time, not the recipe
    ps = {n: p for n, p in sig.parameters.items()
          if n != "self" and n not in supplied and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
    var_kw = any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values())
    out = {}
    for key, value in params.items():
        kp = f"{path}.{key}" if path else str(key)
        if key in supplied:
            raise RecipeError(f"{kp}: supplied by the model that builds {label}, not a recipe parameter")
        if key not in ps:
            if var_kw:
                out[key] = value
                continue
            raise RecipeError(f"{kp}: unknown parameter of {label}{did_you_mean(key, ps)}")
        default = ps[key].default
        if isinstance(value, dict) and "name" not in value and _is_component(hints.get(key)):
            if isinstance(default, str):
                value = {"name": default, **value}  # `conv: {length: 3}` keeps the default conv
            elif _is_spec_mapping(default):
                value = {**default, **value}  # `representation: {scaling: std}` keeps the default's name
        out[key] = convert(value, hints.get(key, ps[key].annotation), kp, registry)
    for name, p in ps.items():
        if p.default is p.empty and name not in out:
            raise RecipeError(f"{path + '.' if path else ''}{name}: missing required parameter of {label}")
        if name not in out and (isinstance(p.default, str) or _is_spec_mapping(p.default)) \
                and _is_component(hints.get(name)):
            # a default component (a name, or a mapping with `name` and parameters) becomes a
            # Spec like a recipe's would
            out[name] = convert(p.default, hints[name], f"{path + '.' if path else ''}{name}", registry)
    return out


def _is_component(tp) -> bool:
    return get_origin(tp) is Annotated and any(isinstance(m, Kind) for m in get_args(tp)[1:])


def _is_spec_mapping(value) -> bool:
    return isinstance(value, dict) and isinstance(value.get("name"), str)


def make_spec(kind: str, value, path: str, registry: Registry | None = None) -> Spec:
    """A validated Spec of ``kind`` from a name or a mapping with ``name`` (``path`` names the
    recipe key in errors). A component built in Python rather than from a recipe normalises its
    nested components with this (``registry`` defaults to the process-wide one)."""
    if isinstance(value, Spec):
        return value
    registry = registry or get_registry()
    if isinstance(value, str):
        name, params = value, {}
    elif isinstance(value, dict):
        if "name" not in value:
            raise RecipeError(f"{path}: a {kind} needs a `name` (registered: {', '.join(registry.names(kind))})")
        params = {k: v for k, v in value.items() if k != "name"}
        name = value["name"]
    else:
        raise RecipeError(f"{path}: expected a {kind} name or a mapping with `name`, got {value!r}")
    cls = registry.get(kind, name, key_path=f"{path}.name" if isinstance(value, dict) else path)
    params = validate_params(cls, params, path, registry, label=name)
    if kind == "dataset" and "units" in params:  # a dataset's `units` names its meshes' unit (Template.units)
        check_units(params["units"], f"{path}.units")
    return Spec(kind, name, params, cls, path)


def convert(value, tp, path: str, registry: Registry):
    """``value`` checked against the annotation ``tp`` and converted (components to Specs, dataclass
    mappings to instances); a RecipeError names ``path``."""
    if tp is inspect.Parameter.empty or tp is Any:
        return value
    if get_origin(tp) is Annotated:
        base, *meta = get_args(tp)
        kinds = [m for m in meta if isinstance(m, Kind)]
        if kinds:
            kind = kinds[0].kind
            if value is None:
                return None
            b_origin = get_origin(base)
            if b_origin in (typing.Union, types.UnionType):
                base = next((a for a in get_args(base) if a is not type(None)), base)
                b_origin = get_origin(base)
            if b_origin is dict:
                if not isinstance(value, dict):
                    raise RecipeError(f"{path}: expected a mapping of label -> {kind}, got {value!r}")
                return {k: make_spec(kind, v, f"{path}.{k}", registry) for k, v in value.items()}
            if b_origin in (list, tuple):
                if not isinstance(value, (list, tuple)):
                    value = [value]
                return [make_spec(kind, v, f"{path}[{i}]", registry) for i, v in enumerate(value)]
            return make_spec(kind, value, path, registry)
        return convert(value, base, path, registry)
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return convert(value, a, path, registry)
            except RecipeError as exc:
                errors.append(exc)
        if len(errors) == 1:
            raise errors[0]
        raise RecipeError(f"{path}: expected {_type_name(tp)}, got {type(value).__name__} {value!r}")
    if origin is typing.Literal:
        if value not in get_args(tp):
            raise RecipeError(f"{path}: expected one of {', '.join(map(repr, get_args(tp)))}, got {value!r}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise RecipeError(f"{path}: expected a list, got {type(value).__name__} {value!r}")
        args = get_args(tp)
        item = args[0] if args and (origin is list or (len(args) == 2 and args[1] is Ellipsis)) else Any
        conv = [convert(v, item, f"{path}[{i}]", registry) for i, v in enumerate(value)]
        return conv if origin is list else tuple(conv)
    if origin is dict:
        if not isinstance(value, dict):
            raise RecipeError(f"{path}: expected a mapping, got {type(value).__name__} {value!r}")
        args = get_args(tp)
        vt = args[1] if len(args) == 2 else Any
        return {k: convert(v, vt, f"{path}.{k}", registry) for k, v in value.items()}
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, tp):
            return value
        if value is None:
            return tp()
        return tp(**validate_params(tp, value, path, registry, label=path.split(".")[-1] or tp.__name__))
    if tp is bool:
        if not isinstance(value, bool):
            raise RecipeError(f"{path}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise RecipeError(f"{path}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            if isinstance(value, str):
                try:
                    return float(value)  # YAML reads 1e-3 as a string
                except ValueError:
                    pass
            raise RecipeError(f"{path}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise RecipeError(f"{path}: expected a string, got {type(value).__name__} {value!r}")
        return value
    if tp in (dict, list):
        if not isinstance(value, tp):
            raise RecipeError(f"{path}: expected a {tp.__name__}, got {type(value).__name__} {value!r}")
    return value


@dataclass
class Resolved:
    """A validated recipe: the task spec, the seed, the train config and the plain data;
    ``seeds``: the recipe's ``seeds:`` as a list (None without it; see ``fwk.runs.run_seeds``)."""

    name: str
    task: Spec
    seed: int
    train: Any
    data: dict
    source: str | None = None
    seeds: list[int] | None = None


def parse_seeds(value, path: str = "seeds") -> list[int] | None:
    """A recipe's ``seeds:``: None (absent), a count n (seeds 0..n-1) or a list of distinct
    integers >= 0, as a list; a RecipeError naming ``path`` otherwise."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, list, tuple)):
        raise RecipeError(f"{path}: expected a number of seeds or a list of seeds, got {value!r}")
    if isinstance(value, int):
        if value < 1:
            raise RecipeError(f"{path}: expected at least one seed, got {value}")
        return list(range(value))
    seeds = [convert(v, int, f"{path}[{i}]", None) for i, v in enumerate(value)]
    if not seeds:
        raise RecipeError(f"{path}: an empty list; give at least one seed")
    if any(s < 0 for s in seeds):
        raise RecipeError(f"{path}: seeds must be >= 0, got {seeds}")
    if len(set(seeds)) != len(seeds):
        raise RecipeError(f"{path}: a seed is given twice ({seeds})")
    return seeds


def resolve(data: dict, registry: Registry) -> Resolved:
    """Validate a loaded recipe against the registry (raises RecipeError with the key path)."""
    data = dict(data)
    source = data.pop("_source", None) or data.get("source")
    if "task" not in data:
        raise RecipeError(f"task: missing; choices: {', '.join(registry.names('task'))}")
    task_name = data["task"]
    if isinstance(task_name, dict):
        raise RecipeError("task: expected a task name; its parameters are the recipe's top-level keys")
    name = data.get("name") or "run"
    if not isinstance(name, str):
        raise RecipeError(f"name: expected a string, got {name!r}")
    seed = convert(data.get("seed", 0), int, "seed", registry)
    seeds = parse_seeds(data.get("seeds"))
    train = convert(data.get("train") or {}, TrainConfig, "train", registry)
    cls = registry.get("task", task_name, key_path="task")
    params = {k: v for k, v in data.items() if k not in RESERVED}
    params = validate_params(cls, params, "", registry, label=f"task {task_name}")
    spec = Spec("task", task_name, params, cls, "")
    plain = {k: v for k, v in data.items()}
    return Resolved(name, spec, seed, train, plain, source, seeds)
