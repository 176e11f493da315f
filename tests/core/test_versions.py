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
