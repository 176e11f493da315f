"""Reusable contract suites (one per kind) and test helpers for built-in and third-party plugins.

Subclass a suite in your own tests::

    from fwk.testing.metric import MetricContract
    class TestMyMetric(MetricContract):
        component = MyMetric
"""
from __future__ import annotations

import os
import pkgutil
import subprocess
from contextlib import contextmanager
from pathlib import Path

import pytest

# The suites' asserts show actual against expected (pytest rewrites a test module's asserts, not
# an installed package's): every submodule is marked before it is imported, whoever imports it
# first (a test module's `from fwk.testing.conv import ConvContract` imports this package first).
# The package itself is in sys.modules already while this runs, so it is not marked (pytest would
# warn that it cannot be rewritten); it holds no assert.
pytest.register_assert_rewrite(*(f"{__name__}.{m.name}" for m in pkgutil.iter_modules(__path__)))

ICT_ENV = "FWK_ICT_PATH"


def build(component: type, params: dict | None = None, path: str = "params"):
    """``component`` built as a recipe builds it: ``params`` checked against its constructor and
    nested components (``Annotated[Spec, Kind(...)]``) resolved against the plugin registry
    (``fwk.recipes.validate_params``), so a suite hands a component what ``fwk run`` hands it."""
    from fwk.plugins import get_registry
    from fwk.recipes import validate_params

    return component(**validate_params(component, dict(params or {}), path, get_registry()))


@contextmanager
def fixed_threads():
    """One thread count for a fit a suite compares bit for bit with another: the environment's
    (``FWK_THREADS``, an executor's ``FWK_ALLOCATED_CPUS``, ``OMP_NUM_THREADS``) where it gives one,
    else 1. Thread counts change the order of floating-point sums, and a trainer takes its count
    from the machine's load as it starts (``fwk.engine.threads.thread_budget``), so two fits of one
    seed in a busy test process (pytest -n 2, the other worker training or not) could differ in the
    last bits. The count is pinned (``fwk.engine.threads.pin``) and set on torch and the BLAS pools
    around the fit, and put back afterwards."""
    import torch
    from threadpoolctl import threadpool_limits

    from fwk.engine import threads as th

    given = th.explicit_threads()
    n = given[0] if given is not None else 1
    pinned, before = th.pinned(), torch.get_num_threads()
    th.pin(n, "fwk.testing.fixed_threads")
    torch.set_num_threads(n)
    try:
        with threadpool_limits(limits=n, user_api="blas"):
            yield n
    finally:
        torch.set_num_threads(before)
        if pinned is None:
            th.unpin()
        else:
            th.pin(*pinned)


def ict_path() -> Path | None:
    """The unpacked ICT-FaceKit FaceXModel folder, or None when it is not available.

    Looks at ``$FWK_ICT_PATH``, then ``shared/data/ict-facekit`` beside or above the repo
    (unpacking the archive with its ``unpack`` script when only the archive is there).
    """
    env = os.environ.get(ICT_ENV)
    if env:
        p = Path(env)
        return p if (p / "generic_neutral_mesh.obj").exists() else None
    here = Path(__file__).resolve()
    for base in [Path.cwd(), *here.parents]:
        d = base / ".." / "shared" / "data" / "ict-facekit"  # name-ok: the data folder beside the repo
        if (d / "FaceXModel" / ".complete").exists():
            return (d / "FaceXModel").resolve()
        if (d / "unpack").exists() and (d / "FaceXModel.tar.xz").exists():
            try:
                out = subprocess.run(["sh", str(d / "unpack")], capture_output=True, text=True, timeout=300)
                p = Path(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 and out.stdout.strip() else None
                if p and (p / "generic_neutral_mesh.obj").exists():
                    return p.resolve()
            except Exception:
                return None
    return None


ICT_SKIP_REASON = (
    "ICT-FaceKit's FaceXModel folder (https://github.com/ICT-VGL/ICT-FaceKit) not found: set "
    "FWK_ICT_PATH to it (docs/quickstart.md, 'The ICT-FaceKit data')"
)
