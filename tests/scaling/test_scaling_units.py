"""The small parts of fwk's DDP launcher, without a training: where a rank finds the recipe, which
state DDP must not broadcast, how many processes ``devices`` means, ranks dying with rank 0."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from fwk.engine.config import TrainConfig
from fwk.engine.distributed import run_root, sparse_state, wants_ddp
from fwk.engine.trainer import _world_size
from fwk.errors import FwkError


def test_a_rank_finds_the_nearest_recipe(tmp_path):
    (tmp_path / "run" / "member" / "reconstruct").mkdir(parents=True)
    (tmp_path / "run" / "recipe.yaml").write_text("task: grid\n")
    assert run_root(tmp_path / "run" / "member" / "reconstruct") == tmp_path / "run"
    (tmp_path / "run" / "member" / "recipe.yaml").write_text("task: reconstruct\n")  # a grid member's own
    assert run_root(tmp_path / "run" / "member" / "reconstruct") == tmp_path / "run" / "member"
    with pytest.raises(FwkError, match="start it with fwk run"):
        run_root(tmp_path / "elsewhere")


def test_sparse_state_is_named():
    m = torch.nn.Linear(3, 2)
    m.register_buffer("pool", torch.eye(3).to_sparse())
    m.register_buffer("dense", torch.zeros(2))
    assert sparse_state(m) == ["pool"]


def test_devices_to_processes():
    assert _world_size(2, True) == 2 and _world_size("3", True) == 3 and _world_size([0, 1], False) == 2
    assert _world_size("auto", True) == 1 and _world_size(-1, True) == 1
    assert wants_ddp(TrainConfig(strategy="ddp")) and not wants_ddp(TrainConfig(strategy="single_device"))
    assert not wants_ddp(TrainConfig())


def _state(pid: int) -> str | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()[0]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_rank_dies_with_rank_0():
    code = ("import subprocess, sys, time\n"
            "from fwk.engine.distributed import die_with_parent\n"
            "c = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], preexec_fn=die_with_parent)\n"
            "print(c.pid, flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    assert _state(child) not in (None, "Z", "X")
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    t0 = time.monotonic()
    while _state(child) not in (None, "Z", "X") and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    assert _state(child) in (None, "Z", "X")
