"""The architecture's rules, checked on the source (issue 12's "Done when").

* No component probes another's API: ``hasattr``, ``inspect.signature`` and ``except TypeError``
  appear in framework/ and plugins/ only on lines whose comment says ``justified:`` why.
* No component names another: a string literal equal to a built-in component's name appears in
  framework/ and plugins/ only as a component's own ``name = "..."``, a constructor parameter's
  default (a recipe parameter with a default, resolved like any Spec), inside a docstring, or on
  a line whose comment says ``name-ok:`` why.
* The core never imports a plugin; plugins never import each other.
"""
from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

from fwk.plugins import get_registry

REPO = Path(__file__).resolve().parents[2]
SOURCES = sorted([*(REPO / "framework").rglob("*.py"), *(REPO / "plugins").rglob("*.py")])
PROBES = re.compile(r"\bhasattr\s*\(|\binspect\s*\.\s*signature\b|\bexcept\s+\(?\s*TypeError\b")


def _comments(text: str) -> dict[int, str]:
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string
    return out


def _code_lines(text: str):
    """(line number, code) with comments and string literals (docstrings too) left out."""
    lines: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type in (tokenize.COMMENT, tokenize.STRING, tokenize.NL, tokenize.NEWLINE):
            continue
        lines[tok.start[0]] = lines.get(tok.start[0], "") + " " + tok.string
    return sorted(lines.items())


def test_no_api_probes_without_a_justifying_comment():
    bad = []
    for path in SOURCES:
        text = path.read_text()
        comments = _comments(text)
        for i, line in _code_lines(text):
            code = line.split("#", 1)[0]
            if PROBES.search(code) and "justified:" not in comments.get(i, ""):
                bad.append(f"{path.relative_to(REPO)}:{i}: {line.strip()}")
    assert not bad, "API probes without a `# justified:` comment:\n" + "\n".join(bad)


def _builtin_names() -> set[str]:
    reg = get_registry()
    return {e.name for e in reg if not e.plugin.startswith(("example", "fwk_example"))}


def _exempt_nodes(tree) -> set[int]:
    """ids of string constants that are allowed: docstrings, parameter defaults, `name = "..."`."""
    ok: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ok.add(id(body[0].value))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            for d in [*node.args.defaults, *[d for d in node.args.kw_defaults if d is not None]]:
                for sub in ast.walk(d):
                    ok.add(id(sub))
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            t = node.targets[0]
            if isinstance(t, ast.Name) and t.id == "name" and isinstance(node.value, ast.Constant):
                ok.add(id(node.value))
    return ok


def test_no_component_names_another():
    names = _builtin_names()
    assert {"spectral", "euclidean", "pbs", "dsm"} <= names
    bad = []
    for path in SOURCES:
        text = path.read_text()
        tree = ast.parse(text)
        comments = _comments(text)
        ok = _exempt_nodes(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names \
                    and id(node) not in ok and "name-ok:" not in comments.get(node.lineno, ""):
                line = text.splitlines()[node.lineno - 1].strip()
                bad.append(f"{path.relative_to(REPO)}:{node.lineno}: {node.value!r} in {line}")
    assert not bad, "quoted names of built-in components (pass them as recipe parameters):\n" + "\n".join(bad)


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def test_core_never_imports_a_plugin_and_plugins_not_each_other():
    for path in (REPO / "framework").rglob("*.py"):
        assert not {m for m in _imports(path) if m.startswith("fwk_")}, path
    for path in (REPO / "plugins").rglob("*.py"):
        own = path.relative_to(REPO / "plugins").parts[1]
        others = {m for m in _imports(path) if m.startswith("fwk_") and m != own}
        assert not others, f"{path} imports {others}"


@pytest.mark.parametrize("kind", ["assemblers", "convs", "datasets", "metrics", "models", "representations",
                                  "samplers", "tasks"])
def test_layout_shows_the_kinds(kind):
    """plugins/<kind>/<package>/: every package under a kind folder registers components of that kind."""
    reg = get_registry()
    hook_kind = kind[:-1]
    for pkg in sorted((REPO / "plugins" / kind).iterdir()):
        if not (pkg / "__init__.py").exists():
            continue
        plugin_entries = [e for e in reg if e.component.__module__.split(".")[0] == pkg.name]
        assert plugin_entries, f"{pkg} registers nothing"
        assert any(e.kind == hook_kind for e in plugin_entries), f"{pkg} registers no {hook_kind}"


# ----------------------------------------------------------------------------- import layers

FWK = REPO / "framework" / "fwk"
ARCHITECTURE = REPO / "docs" / "architecture.md"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(FWK.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_nodes(tree) -> set[int]:
    """ids of the import statements under ``if TYPE_CHECKING:`` (annotations only: never run)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for stmt in node.body:
                out |= {id(sub) for sub in ast.walk(stmt)}
    return out


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {fwk module it imports: line}, every import statement of framework/fwk counted
    wherever it stands (a deferred import inside a function is still a dependency), except those
    under ``if TYPE_CHECKING:``. ``from .x import name`` counts as an import of ``x.name`` where that
    is a module, else of ``x``."""
    files = {_module_name(p): p for p in FWK.rglob("*.py")}
    graph: dict[str, dict[str, int]] = {}
    for mod, path in files.items():
        tree = ast.parse(path.read_text())
        skip = _type_checking_nodes(tree)
        package = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
        out: dict[str, int] = {}
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package[:len(package) - (node.level - 1)]
                    base = ".".join([*up, *([node.module] if node.module else [])])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            for t in targets:
                while t and t not in files:  # `import fwk.engine.config` names a module; a name inside one
                    t = t.rpartition(".")[0]
                if t and t != mod and t.split(".")[0] == "fwk":
                    out.setdefault(t, node.lineno)
        graph[mod] = out
    return graph


def declared_layers() -> list[tuple[str, list[str]]]:
    """The import layers, bottom up, as docs/architecture.md declares them (its "Import layers"
    block: one line per layer, ``N. name: module module ...``)."""
    text = ARCHITECTURE.read_text()
    block = text.split("<!-- import layers -->", 2)
    assert len(block) == 3, "docs/architecture.md lost its <!-- import layers --> block"
    layers = []
    for line in block[1].splitlines():
        m = re.match(r"\s*\d+\.\s+([^:]+):\s+(.+)", line)
        if m:
            layers.append((m.group(1).strip(), m.group(2).split()))
    return layers


def _layer_of(mod: str, layers) -> int | None:
    """The layer of the longest declared prefix of ``mod`` (``fwk`` itself names only the package)."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(layers):
        for p in prefixes:
            if (mod == p or (p != "fwk" and mod.startswith(p + "."))) and len(p) > best_len:
                best, best_len = i, len(p)
    return best


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_core_has_no_import_cycle():
    graph = import_graph()
    assert {"fwk.runs", "fwk.engine.distributed", "fwk.evaluation.curves"} <= set(graph)
    cycles = _cycles(graph)
    detail = [" <-> ".join(c) + ":\n" + "\n".join(f"    {a} imports {b} (line {graph[a][b]})"
                                                  for a in c for b in graph[a] if b in c) for c in cycles]
    assert not cycles, "import cycles in framework/fwk:\n" + "\n".join(detail)


def test_every_import_goes_down_the_declared_layers():
    """docs/architecture.md's import layers: every module of framework/fwk has one, and imports
    only from its own layer or those below it."""
    layers = declared_layers()
    assert len(layers) >= 5, layers
    graph = import_graph()
    unplaced = sorted(m for m in graph if _layer_of(m, layers) is None)
    assert not unplaced, f"modules without a layer in docs/architecture.md's import layers: {unplaced}"
    upward = []
    for mod, targets in sorted(graph.items()):
        own = _layer_of(mod, layers)
        for t, line in sorted(targets.items()):
            if _layer_of(t, layers) > own:
                upward.append(f"{mod} (layer {own + 1}, {layers[own][0]}) imports {t} (layer "
                              f"{_layer_of(t, layers) + 1}, {layers[_layer_of(t, layers)][0]}) on line {line}")
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_the_import_checks_see_a_loop_and_an_upward_import():
    """The checks themselves: a cycle and an upward import are found (fixtures, not fwk's code)."""
    assert _cycles({"a": {"b": 1}, "b": {"a": 2}, "c": {"a": 3}}) == [["a", "b"]]
    layers = [("low", ["fwk", "fwk.errors", "fwk.engine"]), ("high", ["fwk.runs", "fwk.engine.cli"])]
    assert _layer_of("fwk.engine.trainer", layers) == 0
    assert _layer_of("fwk.engine.cli", layers) == 1
    assert _layer_of("fwk.seeds", layers) is None  # `fwk` names the package only


def test_no_class_scoped_fixture_is_an_instance_method():
    """pytest 9.1 deprecates a class-scoped fixture defined as an instance method
    (PytestRemovedIn10Warning; pytest 10 refuses it): such fixtures are classmethods."""
    bad = []
    paths = sorted([*SOURCES, *(REPO / "tests").rglob("*.py"), *(REPO / "examples").rglob("*.py")])
    for path in paths:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef):
                continue
            for fn in node.body:
                if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                decos = [ast.unparse(d) for d in fn.decorator_list]
                class_scoped = any("fixture" in d and re.search(r"scope\s*=\s*['\"]class['\"]", d) for d in decos)
                if class_scoped and not any(d in ("classmethod", "staticmethod") for d in decos):
                    bad.append(f"{path.relative_to(REPO)}:{fn.lineno}: {node.name}.{fn.name}")
    assert not bad, "class-scoped fixtures defined as instance methods (add @classmethod under the fixture):\n" + \
        "\n".join(bad)
