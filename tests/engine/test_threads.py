"""fwk.engine.threads: the live fwk processes share the cores (no timing assertions)."""
import json
import os
import subprocess
import sys

import pytest
import torch

from fwk.engine import threads
from fwk.engine.threads import apply_threads, live_processes, register, runtime_dir, thread_budget, unregister
from fwk.errors import FwkError

NOENV = {}  # neither FWK_THREADS nor OMP_NUM_THREADS


@pytest.fixture
def procs(tmp_path, monkeypatch):
    d = tmp_path / "procs"
    monkeypatch.setenv("FWK_RUNTIME_DIR", str(d))
    yield d
    unregister()


@pytest.fixture
def torch_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def _registered_child(d):
    """Another process, registered the way fwk registers, alive until killed."""
    code = ("import sys, time; from pathlib import Path; from fwk.engine.threads import register; "
            "register(Path(sys.argv[1])); print('ready', flush=True); time.sleep(120)")
    p = subprocess.Popen([sys.executable, "-c", code, str(d)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    return p


def test_two_registrations_halve_the_cores(procs):
    register()
    assert live_processes() == [os.getpid()]
    assert thread_budget(NOENV, cores=4) == (4, "1 fwk process on 4 cores")
    child = _registered_child(procs)
    try:
        assert live_processes() == sorted([os.getpid(), child.pid])
        assert thread_budget(NOENV, cores=4) == (2, "2 fwk processes on 4 cores")
        assert thread_budget(NOENV, cores=2)[0] == 1
        assert thread_budget(NOENV, cores=3)[0] == 1  # 3 // 2
        assert thread_budget(NOENV, cores=1)[0] == 1  # never 0
    finally:
        child.kill()
        child.wait()
    # the child died without unregistering: ignored, and its file removed
    assert thread_budget(NOENV, cores=4)[0] == 4
    assert sorted(p.name for p in procs.iterdir()) == [str(os.getpid())]


def test_an_unregistered_process_counts_itself(procs):
    child = _registered_child(procs)
    try:
        assert thread_budget(NOENV, cores=4)[0] == 2  # the child and this process
    finally:
        child.kill()
        child.wait()
    assert thread_budget(NOENV, cores=4)[0] == 4


def test_dead_and_reused_pids_are_ignored_and_removed(procs):
    procs.mkdir(parents=True)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    (procs / str(gone.pid)).write_text(f"{gone.pid} 1\n")  # exited
    ppid = os.getppid()
    (procs / str(ppid)).write_text(f"{ppid} 1\n")  # alive, but started later than tick 1: a reused pid
    (procs / "123abc").write_text("junk")  # not a registration: left alone
    (procs / "77").write_text("garbage")  # unreadable registration: removed
    assert live_processes() == []
    assert thread_budget(NOENV, cores=2, directory=procs)[0] == 2
    assert sorted(p.name for p in procs.iterdir()) == ["123abc"]


def test_register_is_idempotent_and_unregister_removes_the_file(procs):
    a = register()
    assert register() == a and a.read_text().split()[0] == str(os.getpid())
    unregister()
    assert not a.exists()
    unregister()  # twice is fine


def test_explicit_counts_win():
    assert thread_budget({"FWK_THREADS": "3", "OMP_NUM_THREADS": "1"}, cores=2, live=2) == (3, "FWK_THREADS=3")
    assert thread_budget({"OMP_NUM_THREADS": "1"}, cores=8, live=1) == (1, "OMP_NUM_THREADS=1")
    assert thread_budget({"OMP_NUM_THREADS": "4,2"}, cores=8, live=1)[0] == 4  # one value per nesting level
    assert thread_budget({"FWK_THREADS": "auto"}, cores=8, live=2)[0] == 4
    assert thread_budget({"OMP_NUM_THREADS": "nonsense"}, cores=8, live=2)[0] == 4
    for bad in ("0", "-1", "x"):
        with pytest.raises(FwkError, match="FWK_THREADS"):
            thread_budget({"FWK_THREADS": bad}, cores=8, live=1)


def test_an_executors_allocation_replaces_the_count_of_live_processes():
    """A Ray member (FWK_ALLOCATED_CPUS) computes with its allocation, whatever else runs and
    whatever OMP_NUM_THREADS Ray set; an explicit FWK_THREADS still wins."""
    alloc = {"FWK_ALLOCATED_CPUS": "3", "OMP_NUM_THREADS": "1"}
    assert thread_budget(alloc, cores=8, live=4) == (3, "3 CPUs allocated to this process")
    assert thread_budget({"FWK_ALLOCATED_CPUS": "1"}, cores=8, live=1) == (1, "1 CPU allocated to this process")
    assert thread_budget({**alloc, "FWK_THREADS": "2"}, cores=8, live=4) == (2, "FWK_THREADS=2")
    with pytest.raises(FwkError, match="FWK_ALLOCATED_CPUS"):
        thread_budget({"FWK_ALLOCATED_CPUS": "0"}, cores=8, live=1)


def test_a_ddp_training_splits_the_allocation_among_its_ranks(monkeypatch):
    from fwk.engine.distributed import DistEnv

    monkeypatch.setenv("FWK_ALLOCATED_CPUS", "4")
    monkeypatch.delenv("MASTER_PORT", raising=False)
    with DistEnv(2):
        assert os.environ["FWK_ALLOCATED_CPUS"] == "2"
        os.environ["MASTER_PORT"] = "12345"  # what the launcher sets
    assert os.environ["FWK_ALLOCATED_CPUS"] == "4" and "MASTER_PORT" not in os.environ


def test_runtime_dir(monkeypatch, tmp_path):
    monkeypatch.delenv("FWK_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert runtime_dir() == tmp_path / "fwk" / "procs"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert runtime_dir().name == "procs" and runtime_dir().parent.name == f"fwk-{os.getuid()}"
    monkeypatch.setenv("FWK_RUNTIME_DIR", str(tmp_path / "x"))
    assert runtime_dir() == tmp_path / "x"


def test_a_folder_of_another_user_is_not_used(procs, monkeypatch):
    uid = os.getuid()
    monkeypatch.setattr(threads.os, "getuid", lambda: uid + 1)
    assert register() is None
    assert thread_budget(NOENV, cores=2)[0] == 2


def test_apply_threads_and_the_per_epoch_recheck(procs, monkeypatch, torch_threads):
    from fwk.engine import ThreadShare

    monkeypatch.setattr(threads, "available_cores", lambda: 4)
    monkeypatch.delenv("FWK_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    register()
    torch.set_num_threads(1)
    assert apply_threads() == (4, "1 fwk process on 4 cores", True)
    assert torch.get_num_threads() == 4 and apply_threads()[2] is False
    said = []
    share = ThreadShare(said.append)
    child = _registered_child(procs)  # a second run starts: the first gives up threads at its next epoch
    try:
        share.on_train_epoch_start(None, None)
        assert torch.get_num_threads() == 2 and said == ["threads: 2 (2 fwk processes on 4 cores)"]
        share.on_train_epoch_start(None, None)
        assert len(said) == 1  # no change, nothing said
    finally:
        child.kill()
        child.wait()
    share.on_train_epoch_start(None, None)  # ... and takes them back when it ends
    assert torch.get_num_threads() == 4 and said[-1] == "threads: 4 (1 fwk process on 4 cores)"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    share.on_train_epoch_start(None, None)
    assert torch.get_num_threads() == 1


def test_fit_records_the_thread_count_of_every_epoch(procs, monkeypatch, tmp_path, torch_threads):
    from test_early_stopping import _ctx, _data, _module

    from fwk.engine import fit

    monkeypatch.setattr(threads, "available_cores", lambda: 4)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("FWK_THREADS", "auto")
    child = _registered_child(procs)
    try:
        train, val = _data()
        ctx = _ctx(tmp_path, epochs=2)
        fit(_module(), train, val, ctx, "reg")
        assert (procs / str(os.getpid())).exists()  # fit registered this process
    finally:
        child.kill()
        child.wait()
    r = json.loads((ctx.run_dir / "curves" / "reg.json").read_text())
    assert [e["threads"] for e in r["epochs"]] == [2, 2]


def test_fwk_threads_option_sets_the_variable(monkeypatch):
    from fwk.cli import main

    monkeypatch.delenv("FWK_THREADS", raising=False)
    assert main(["list", "--kind", "metric", "--threads", "3"]) == 0
    assert os.environ["FWK_THREADS"] == "3"
    monkeypatch.delenv("FWK_THREADS")
    with pytest.raises(SystemExit):
        main(["--threads", "0", "list"])


def test_thread_share_reports_inside_a_real_trainer(monkeypatch, tmp_path):
    """Lightning sets every callback's ``log`` to the module's: the change must still reach the
    run's log (a regression: it called LightningModule.log with one argument)."""
    import lightning.pytorch as pl

    from fwk.engine import ThreadShare
    from fwk.engine import callbacks as cb

    calls = iter([(1, "2 fwk processes on 2 cores", True)] + [(1, "", False)] * 10)
    monkeypatch.setattr(cb, "apply_threads", lambda *a, **k: next(calls))

    class Tiny(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Linear(2, 1)

        def training_step(self, batch, _):
            return self.w(batch[0]).square().mean()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    said = []
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(4, 2)), batch_size=2)
    trainer = pl.Trainer(max_epochs=2, callbacks=[ThreadShare(said.append)], logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(tmp_path))
    trainer.fit(Tiny(), data)
    assert said == ["threads: 1 (2 fwk processes on 2 cores)"]
