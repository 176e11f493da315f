"""Meta-test: every hookspec is documented and exercised by a test."""
import inspect
from pathlib import Path

from fwk import hookspecs


def test_every_hookspec_documented_and_exercised():
    here = Path(__file__).resolve().parents[1]
    tests = "\n".join(p.read_text() for p in here.rglob("*.py") if p.name != Path(__file__).name)
    for kind in hookspecs.KINDS:
        name = hookspecs.HOOKS[kind]
        fn = getattr(hookspecs, name)
        assert inspect.getdoc(fn), f"{name} has no docstring"
        assert name in tests, f"no test implements or calls {name}"
