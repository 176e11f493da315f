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
import math
import os
import re
import stat
import types
import typing
from collections.abc import Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, get_args, get_origin

import yaml

from .data.template import check_units
from .engine.config import TrainConfig
from .errors import RecipeError, cut, quote
from .plugins import get_registry
from .protocols import KIND_ROLES, missing_members, role_members
from .registry import Registry, did_you_mean

#: the largest integer a recipe may give (a signed 64-bit integer's)
MAX_INT = 2**63 - 1
#: the seeds ``seed:`` accepts (Lightning's seed_everything takes unsigned 32-bit seeds)
MAX_SEED = 2**32 - 1
#: the most seeds a recipe's ``seeds:`` may list (each trains every model once)
MAX_SEEDS = 1000
#: the longest run name (the run directory adds ``-yyyymmdd-HHMMSS``; a file name has 255 bytes)
MAX_NAME = 100

RESERVED = ("task", "extends", "name", "seed", "seeds", "train", "description", "source")


class Kind:
    """Annotation marker: ``Annotated[Spec, Kind("representation")]``. ``role``: a role of
    ``fwk.protocols`` the component must play beyond its kind's (``Kind("model",
    BlendshapeModel)``), checked when the recipe is validated."""

    def __init__(self, kind: str, role: type | None = None):
        self.kind = kind
        self.role = role

    def __repr__(self):
        return f"Kind({self.kind!r}" + (f", {self.role.__name__})" if self.role is not None else ")")


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
        ``extra``. A ``RecipeError`` its constructor raises names the full recipe path: ``k: ...``
        from the conv of ``models.ae.network`` reads ``models.ae.network.conv.k: ...``; any other
        exception carries a note naming the path."""
        if self.cls is None:
            raise RuntimeError(f"{self.path}: spec of {self.kind} {self.name!r} is not resolved")
        try:
            return self.cls(*args, **{**self.params, **extra})
        except RecipeError as exc:
            if self.path:
                exc.args = (with_key_path(str(exc), self.path),)
            raise
        except Exception as exc:  # a plugin's constructor may raise anything: say which component
            if self.path:
                exc.add_note(f"(raised while building {self.path}: {self.kind} {self.name!r})")
            raise

    def to_dict(self) -> dict:
        """The recipe form: ``{name: ..., parameters...}``."""
        return {"name": self.name, **{k: to_plain(v) for k, v in self.params.items()}}


_KEY = re.compile(r"[A-Za-z_][\w-]*(?:\[\d+\]|\.[\w+-]+)*")


def with_key_path(message: str, path: str) -> str:
    """``message`` (a RecipeError's) prefixed with the recipe path ``path`` it happened under:
    ``k: must be >= 1`` becomes ``path.k: must be >= 1``; a message that names no key of its own
    becomes ``path: message``; one that already starts with ``path`` is kept."""
    if not path or message == path or message.startswith((f"{path}.", f"{path}:", f"{path}[")):
        return message
    head = message.split(":", 1)[0]
    if ":" in message and _KEY.fullmatch(head):
        if "." in head and head.split(".")[0] == path.split(".")[0]:
            return message  # a full path already (another component's, under the same recipe key)
        return f"{path}.{message}"
    return f"{path}: {message}"


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

#: the largest recipe file read (a recipe is a few kilobytes; a bigger one is a mistake or an attack)
MAX_RECIPE_BYTES = 1 << 20
#: the most YAML nodes a recipe may hold once its aliases are expanded (``*name`` repeats the
#: node ``&name`` anchors; nested aliases grow exponentially, the "billion laughs")
MAX_RECIPE_NODES = 100_000


class RecipeLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader (no Python objects), refusing a key given twice in one mapping (both
    line numbers named) and a document whose aliases expand past ``MAX_RECIPE_NODES`` nodes."""

    source = "recipe"

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}  # key -> the line it was first given on
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base`: explicit keys override it
                    continue
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                if not isinstance(key, Hashable):
                    continue  # a list or mapping as a key: PyYAML's own error follows
                first = seen.get(key)
                if first is not None:
                    raise RecipeError(f"{self.source}, line {line}: key {quote(key)} given twice "
                                      f"(first on line {first})")
                seen[key] = line
        return super().construct_mapping(node, deep=deep)

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            n = _expanded_size(node, {}, set(), self.source)
            if n > MAX_RECIPE_NODES:
                raise RecipeError(f"{self.source}: more than {MAX_RECIPE_NODES:,} values once its aliases (*name) "
                                  f"are expanded; a recipe repeats a part with extends: or an override instead")
        return node


def _expanded_size(node, memo: dict, active: set, source: str = "recipe") -> int:
    """How many nodes ``node`` holds with every alias expanded (counted once per node: O(nodes));
    stops counting past the limit, and refuses an alias of a node inside itself."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in active:
        raise RecipeError(f"{source}: an alias (*name) refers to a node that contains it (a recursive structure)")
    if isinstance(node, yaml.ScalarNode):
        return 1
    active.add(key)
    total = 1
    for item in node.value:
        for child in (item if isinstance(item, tuple) else (item,)):
            total += _expanded_size(child, memo, active, source)
            if total > MAX_RECIPE_NODES:
                break
        if total > MAX_RECIPE_NODES:
            break
    active.discard(key)
    memo[key] = total
    return total


def yaml_load(text: str, source: str = "recipe"):
    """``text`` read as YAML with ``RecipeLoader``; a RecipeError naming ``source`` (and the line)
    for anything wrong."""
    try:
        return _construct(text, source)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}, line {mark.line + 1}" if mark is not None else source
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise RecipeError(f"{where}: not valid YAML ({quote(what)[1:-1]})") from None
    except RecursionError:
        raise RecipeError(f"{source}: nested too deeply") from None


def _construct(text: str, source: str):
    loader = RecipeLoader(text)
    loader.source = source
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_recipe_text(path: Path, what: str = "recipe file") -> str:
    """The text of the recipe file ``path``: a regular file (not a folder, a device or a FIFO,
    which would block), at most ``MAX_RECIPE_BYTES`` bytes, UTF-8."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opens at once; it is refused below
    except ValueError:  # a NUL in the path
        raise RecipeError(f"{what} {quote(str(path))}: not a valid path") from None
    except FileNotFoundError:
        raise RecipeError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise RecipeError(f"{what} {path} is a folder, not a file") from None
    except OSError as exc:
        raise RecipeError(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise RecipeError(f"{what} {path} is a folder, not a file")
        if not stat.S_ISREG(st.st_mode):
            raise RecipeError(f"{what} {path} is not a regular file (a device, FIFO or socket)")
        if st.st_size > MAX_RECIPE_BYTES:
            raise RecipeError(f"{what} {path}: {st.st_size:,} bytes, more than a recipe may have "
                              f"({MAX_RECIPE_BYTES:,})")
        with os.fdopen(fd, "rb") as f:
            fd = None
            data = f.read(MAX_RECIPE_BYTES + 1)
    except OSError as exc:
        raise RecipeError(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    finally:
        if fd is not None:
            os.close(fd)
    if len(data) > MAX_RECIPE_BYTES:
        raise RecipeError(f"{what} {path}: more than {MAX_RECIPE_BYTES:,} bytes")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise RecipeError(f"{what} {path}, line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); "
                          f"save it as UTF-8") from None


def read_recipe_file(path: Path, what: str = "recipe file") -> dict:
    """A recipe file's mapping, read with every check of ``read_recipe_text`` and ``yaml_load``
    (``extends`` not resolved): for any code that reads a recipe, ``recipe.yaml`` of a run
    included."""
    return _read_yaml(Path(path), what)


def _read_yaml(path: Path, what: str = "recipe file") -> dict:
    data = yaml_load(read_recipe_text(path, what), str(path))
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


def _load_with_extends(path: Path, seen: tuple = (), what: str = "recipe file") -> dict:
    try:
        path = path.resolve()
    except (OSError, ValueError, RuntimeError):  # a NUL in the path, a symlink loop
        raise RecipeError(f"{what} {quote(str(path))}: not a valid path") from None
    if path in seen:
        chain = " -> ".join(str(p.name) for p in (*seen, path))
        raise RecipeError(f"extends: recipes extend each other in a cycle ({chain})")
    data = _read_yaml(path, what)
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str) or not parent:
        raise RecipeError(f"{path.name}: extends: expected a recipe path, got {quote(parent)}")
    base = _load_with_extends((path.parent / parent), (*seen, path), f"{path.name}: extends:")
    return deep_merge(base, data)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b.c=value`` -> (['a', 'b', 'c'], the value read as YAML)."""
    if "=" not in text:
        raise RecipeError(f"override {quote(text)}: expected key.path=value")
    key, _, raw = text.partition("=")
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise RecipeError(f"override {quote(text)}: expected key.path=value")
    try:
        value = _construct(raw, f"override {quote(key)}") if raw.strip() else ""
    except yaml.YAMLError:
        value = raw  # not YAML: the text itself
    except RecursionError:
        raise RecipeError(f"override {quote(key)}: nested too deeply") from None
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
                    raise RecipeError(f"override {quote(text)}: {'.'.join(keys[: i + 1])} is not a mapping")
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

def _key(key) -> str:
    """A recipe key for a key path in an error message, cut like ``fwk.errors.quote``."""
    return cut(str(key))


def check_run_name(name, key: str = "name") -> str:
    """``name`` when it can name a run directory inside the runs folder: a non-empty string of at
    most ``MAX_NAME`` characters without a path separator, ``..``, NUL or another control
    character; else a RecipeError naming ``key``."""
    if not isinstance(name, str):
        raise RecipeError(f"{key}: expected a string, got {type(name).__name__} {quote(name)}")
    if not name.strip():
        raise RecipeError(f"{key}: empty; a run needs a name")
    if len(name) > MAX_NAME:
        raise RecipeError(f"{key}: {len(name):,} characters, at most {MAX_NAME} ({quote(name)})")
    bad = [c for c in ("/", "\\", "\0") if c in name]
    if bad or ".." in name or any(ord(c) < 32 or ord(c) == 127 for c in name):
        what = {"/": "a path separator /", "\\": "a path separator \\", "\0": "a NUL character"}.get(
            bad[0] if bad else "", "`..`" if ".." in name else "a control character")
        raise RecipeError(f"{key}: {quote(name)} contains {what}; a run name is one folder name "
                          f"inside the runs folder")
    return name


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
        raise RecipeError(f"{path}: expected a mapping of parameters, got {quote(params)}")
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
        kp = f"{path}.{_key(key)}" if path else _key(key)
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


def check_role(kind: str, name: str, cls: type, path: str, role: type | None = None) -> None:
    """A RecipeError naming ``path`` and the missing members when ``cls`` does not play its
    kind's role (``fwk.protocols.KIND_ROLES``) or ``role``."""
    for r in [KIND_ROLES.get(kind), role]:
        missing = missing_members(cls, r) if r is not None else []
        if missing:
            family = getattr(cls, "task_family", None) if kind == "model" else None
            what = f"{cls.__module__}.{cls.__qualname__}" + (f", a {family} model" if isinstance(family, str) else "")
            raise RecipeError(f"{path}: {kind} {quote(name)} ({what}) does not play the {r.__name__} role: "
                              f"it lacks {', '.join(missing)} (fwk.protocols.{r.__name__}: "
                              f"{', '.join(role_members(r))})")


def make_spec(kind: str, value, path: str, registry: Registry | None = None, role: type | None = None) -> Spec:
    """A validated Spec of ``kind`` from a name or a mapping with ``name`` (``path`` names the
    recipe key in errors), its class checked to play the kind's role and ``role`` (``check_role``).
    A component built in Python rather than from a recipe normalises its nested components with
    this (``registry`` defaults to the process-wide one)."""
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
        raise RecipeError(f"{path}: expected a {kind} name or a mapping with `name`, got {quote(value)}")
    cls = registry.get(kind, name, key_path=f"{path}.name" if isinstance(value, dict) else path)
    check_role(kind, name, cls, path, role)
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
            kind, role = kinds[0].kind, kinds[0].role
            if value is None:
                return None
            b_origin = get_origin(base)
            if b_origin in (typing.Union, types.UnionType):
                base = next((a for a in get_args(base) if a is not type(None)), base)
                b_origin = get_origin(base)
            if b_origin is dict:
                if not isinstance(value, dict):
                    raise RecipeError(f"{path}: expected a mapping of label -> {kind}, got {quote(value)}")
                return {k: make_spec(kind, v, f"{path}.{_key(k)}", registry, role) for k, v in value.items()}
            if b_origin in (list, tuple):
                if not isinstance(value, (list, tuple)):
                    value = [value]
                return [make_spec(kind, v, f"{path}[{i}]", registry, role) for i, v in enumerate(value)]
            return make_spec(kind, value, path, registry, role)
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
        raise RecipeError(f"{path}: expected {_type_name(tp)}, got {type(value).__name__} {quote(value)}")
    if origin is typing.Literal:
        if value not in get_args(tp):
            raise RecipeError(f"{path}: expected one of {', '.join(map(repr, get_args(tp)))}, got {quote(value)}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise RecipeError(f"{path}: expected a list, got {type(value).__name__} {quote(value)}")
        args = get_args(tp)
        item = args[0] if args and (origin is list or (len(args) == 2 and args[1] is Ellipsis)) else Any
        conv = [convert(v, item, f"{path}[{i}]", registry) for i, v in enumerate(value)]
        return conv if origin is list else tuple(conv)
    if origin is dict:
        if not isinstance(value, dict):
            raise RecipeError(f"{path}: expected a mapping, got {type(value).__name__} {quote(value)}")
        args = get_args(tp)
        vt = args[1] if len(args) == 2 else Any
        return {k: convert(v, vt, f"{path}.{_key(k)}", registry) for k, v in value.items()}
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, tp):
            return value
        if value is None:
            return tp()
        return tp(**validate_params(tp, value, path, registry, label=path.split(".")[-1] or tp.__name__))
    if tp is bool:
        if not isinstance(value, bool):
            raise RecipeError(f"{path}: expected true or false, got {quote(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise RecipeError(f"{path}: expected an integer, got {type(value).__name__} {quote(value)}")
        if not -MAX_INT <= value <= MAX_INT:
            raise RecipeError(f"{path}: {quote(value)} is out of range (at most {MAX_INT} in magnitude, 64 bits)")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            number = None
            if isinstance(value, str):
                try:
                    number = float(value)  # YAML reads 1e-3 as a string
                except ValueError:
                    pass
            if number is None:
                raise RecipeError(f"{path}: expected a number, got {type(value).__name__} {quote(value)}")
            value = number
        try:
            value = float(value)
        except OverflowError:  # an integer beyond a double's range
            raise RecipeError(f"{path}: {quote(value)} is out of range") from None
        if not math.isfinite(value):
            raise RecipeError(f"{path}: expected a finite number, got {value}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise RecipeError(f"{path}: expected a string, got {type(value).__name__} {quote(value)}")
        return value
    if tp in (dict, list):
        if not isinstance(value, tp):
            raise RecipeError(f"{path}: expected a {tp.__name__}, got {type(value).__name__} {quote(value)}")
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
        raise RecipeError(f"{path}: expected a number of seeds or a list of seeds, got {quote(value)}")
    if isinstance(value, int):
        if value < 1:
            raise RecipeError(f"{path}: expected at least one seed, got {value}")
        if value > MAX_SEEDS:
            raise RecipeError(f"{path}: {value} seeds, more than {MAX_SEEDS} (each trains every model once)")
        return list(range(value))
    if len(value) > MAX_SEEDS:
        raise RecipeError(f"{path}: {len(value)} seeds, more than {MAX_SEEDS} (each trains every model once)")
    seeds = [convert(v, int, f"{path}[{i}]", None) for i, v in enumerate(value)]
    if not seeds:
        raise RecipeError(f"{path}: an empty list; give at least one seed")
    bad = [s for s in seeds if not 0 <= s <= MAX_SEED]
    if bad:
        raise RecipeError(f"{path}: seed {bad[0]} is out of range (0 to {MAX_SEED}, 32 bits)")
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
    name = data.get("name")
    name = check_run_name("run" if name is None else name)
    seed = convert(data.get("seed", 0), int, "seed", registry)
    if not 0 <= seed <= MAX_SEED:
        raise RecipeError(f"seed: {seed} is out of range (0 to {MAX_SEED}, 32 bits)")
    seeds = parse_seeds(data.get("seeds"))
    train = convert(data.get("train") or {}, TrainConfig, "train", registry)
    cls = registry.get("task", task_name, key_path="task")
    check_role("task", task_name, cls, "task")
    params = {k: v for k, v in data.items() if k not in RESERVED}
    params = validate_params(cls, params, "", registry, label=f"task {task_name}")
    spec = Spec("task", task_name, params, cls, "")
    plain = {k: v for k, v in data.items()}
    return Resolved(name, spec, seed, train, plain, source, seeds)
