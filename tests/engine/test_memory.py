"""fwk.engine.memory: freed blocks stay in the heap, so the next step's tensors of the same size
fault no pages in; glibc's defaults (and a user's own settings) are left alone when asked."""
import json
import subprocess
import sys

import pytest

from fwk.engine import memory

CHILD = r"""
import json, resource, sys
import torch
from fwk.engine.memory import retain_freed_memory
done = retain_freed_memory() if sys.argv[1] == "keep" else "defaults"
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):  # warm up: the heap grows to the working set
    torch.ones(12_000_000).sum()
per = []
for _ in range(9):
    f0 = faults()
    torch.ones(12_000_000).sum()  # 48 MB, above glibc's largest default mmap threshold (32 MB)
    per.append(faults() - f0)
# the median: a step may still land in fresh heap once (another allocation took part of the freed block)
print(json.dumps({"done": done, "faults_per_tensor": sorted(per)[len(per) // 2]}))
"""


def _child(mode, env=None):
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_kept_memory_faults_no_pages_in_at_the_next_step():
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "FWK_KEEP_FREED_MEMORY"}
    default, kept = _child("defaults", env), _child("keep", env)
    if kept["done"] != "applied":
        pytest.skip(kept["done"])
    # 48 MB is 11,719 pages of 4 KB: every one faults in again with glibc's defaults
    assert default["faults_per_tensor"] > 5_000, default
    assert kept["faults_per_tensor"] < 100, kept


def test_a_users_malloc_settings_and_the_opt_out_win(monkeypatch):
    monkeypatch.setattr(memory, "_applied", None)
    assert memory.retain_freed_memory({"MALLOC_ARENA_MAX": "2", "MALLOC_TRIM_THRESHOLD_": "0"}).startswith("not applied")
    monkeypatch.setattr(memory, "_applied", None)
    assert memory.retain_freed_memory({"FWK_KEEP_FREED_MEMORY": "0"}) == "not applied: FWK_KEEP_FREED_MEMORY=0"
