"""versions.json names the commit a run was made from, and whether tracked files differed from it."""
import subprocess
from pathlib import Path

import pytest

from fwk.plugins import get_registry
from fwk.runs import versions

ROOT = Path(__file__).resolve().parents[2]


def test_commit_and_dirty_flag_match_git():
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode != 0:
        pytest.skip("not a git checkout: versions.json has no commit")
    v = versions(get_registry())
    assert v["git_commit"] == head.stdout.strip()
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                            capture_output=True, text=True).stdout
    assert v["git_dirty"] is bool(status.strip())
    assert v["torch"] and v["plugins"]


def test_library_versions_are_the_modules_own_without_importing_them():
    """versions.json's library versions are what each module says of itself (``__version__``), read from
    the installed distributions: open3d, which a run may never use, is not imported for it."""
    import importlib
    import sys

    v = versions(get_registry())
    for mod in ("numpy", "scipy", "torch", "lightning", "torch_geometric", "trimesh", "pyvista", "open3d"):
        if mod in v:
            assert v[mod] == getattr(importlib.import_module(mod), "__version__", ""), mod
    code = ("import sys; from fwk.plugins import get_registry; from fwk.runs import versions; "
            "versions(get_registry()); print('open3d' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "False", out.stderr[-2000:]
