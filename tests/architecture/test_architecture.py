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
