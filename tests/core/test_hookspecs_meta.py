"""Meta-test: every hookspec is documented and exercised by some test."""
import inspect
from pathlib import Path

from fwk import hookspecs


def test_every_hookspec_documented_and_exercised():
    tests = "\n".join(p.read_text() for p in Path(__file__).resolve().parents[1].rglob("*.py"))
    plugins = Path(__file__).resolve().parents[2] / "plugins"
    for kind in hookspecs.KINDS:
        name = hookspecs.HOOKS[kind]
        fn = getattr(hookspecs, name)
        assert inspect.getdoc(fn), f"{name} has no docstring"
        # exercised: a test registers or looks up this kind
        assert name in tests or f'"{kind}"' in tests, f"no test exercises {name}"
        # implemented by at least one built-in plugin
        assert any(name in p.read_text() for p in plugins.rglob("__init__.py")), f"no built-in implements {name}"
