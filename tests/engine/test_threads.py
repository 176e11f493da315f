"""fwk.engine.threads: the live fwk processes share the cores left free by other work (no timing
assertions). The machine's own load is faked here (``no_outside_load``); the load tests below
build a fake ``/proc``."""
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


@pytest.fixture(autouse=True)
def no_outside_load(request, monkeypatch):
    """The tests of the fwk-process rule run as on an idle machine (the real one is shared)."""
    if "real_load" not in request.fixturenames:
        monkeypatch.setattr(threads, "outside_load", lambda *a, **k: (0.0, 1024))  # none busy, cores the limit


@pytest.fixture
def procs(tmp_path, monkeypatch):
    d = tmp_path / "procs"
    monkeypatch.setenv("FWK_RUNTIME_DIR", str(d))
    yield d
    unregister()


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


# ---- the machine's load: the rule and its measurement, against naive reference computations ----

def _naive_share(cores, live, outside, cpus):
    """The documented rule, written out the slow way."""
    from decimal import ROUND_HALF_UP, Decimal

    taken = int(Decimal(repr(outside)).quantize(Decimal(1), rounding=ROUND_HALF_UP))
    free = cpus - taken
    if free > cores:
        free = cores
    n = 0
    while (n + 1) * live <= free:
        n += 1
    return n if n >= 1 else 1


def test_the_rule_against_a_naive_reference():
    import random

    rnd = random.Random(0)
    cases = [(2, 1, 2.0, 2), (2, 1, 0.0, 2), (2, 1, 0.49, 2), (2, 1, 0.5, 2), (2, 1, 1.5, 2),
             (16, 2, 2.0, 16), (4, 1, 0.0, 64), (4, 1, 62.0, 64), (8, 3, 8.0, 8), (1, 5, 0.0, 1)]
    cases += [(c, rnd.randint(1, 6), round(rnd.uniform(0, cpu), rnd.choice([0, 1, 2, 3])), cpu)
              for c, cpu in ((rnd.randint(1, 64), rnd.randint(1, 64)) for _ in range(2000))]
    for cores, live, outside, cpus in cases:
        assert threads.share(cores, live, outside, cpus) == _naive_share(cores, live, outside, cpus), \
            (cores, live, outside, cpus)
    assert threads.share(2, 1, 2.0) == 1  # beside a 2-thread job on 2 cores: one thread
    assert threads.share(16, 1, 0.0) == 16 and threads.share(16, 2, 0.3) == 8  # no load: cores // live


def test_thread_budget_with_a_faked_load():
    # beside a 2-thread job on 2 cores a training computes with one thread, and says why
    assert thread_budget(NOENV, cores=2, live=1, outside=2.0, cpus=2) == (
        1, "1 fwk process on 2 cores, 2.0 of 2 CPUs busy with other work")
    assert thread_budget(NOENV, cores=16, live=2, outside=3.6, cpus=16) == (
        6, "2 fwk processes on 16 cores, 3.6 of 16 CPUs busy with other work")
    # a cgroup quota of 4 cores on a 64-CPU host half busy: the quota is the limit
    assert thread_budget(NOENV, cores=4, live=1, outside=32.0, cpus=64)[0] == 4
    assert thread_budget(NOENV, cores=4, live=1, outside=0.2, cpus=4) == (4, "1 fwk process on 4 cores")
    # explicit counts still win over the load
    assert thread_budget({"FWK_THREADS": "2"}, cores=2, live=1, outside=2.0) == (2, "FWK_THREADS=2")
    assert thread_budget({"OMP_NUM_THREADS": "2"}, cores=2, live=1, outside=2.0)[0] == 2
    assert thread_budget({"FWK_ALLOCATED_CPUS": "2"}, cores=2, live=1, outside=2.0)[0] == 2


def test_apply_threads_follows_the_measured_load(procs, monkeypatch, torch_threads):
    from fwk.engine import ThreadShare

    monkeypatch.setattr(threads, "available_cores", lambda: 2)
    monkeypatch.delenv("FWK_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    load = [2.0]
    monkeypatch.setattr(threads, "outside_load", lambda *a, **k: (load[0], 2))
    torch.set_num_threads(2)
    assert apply_threads() == (1, "1 fwk process on 2 cores, 2.0 of 2 CPUs busy with other work", True)
    said = []
    share = ThreadShare(said.append)
    load[0] = 0.1  # the other job ended: the next epoch takes the cores back
    share.on_train_epoch_start(None, None)
    assert torch.get_num_threads() == 2 and said == ["threads: 2 (1 fwk process on 2 cores)"]
    monkeypatch.setenv("FWK_THREADS", "2")
    load[0] = 2.0
    share.on_train_epoch_start(None, None)
    assert torch.get_num_threads() == 2


def _stat_line(pid, comm, ppid, start, ticks):
    """A /proc/<pid>/stat line: ticks = (utime, stime, cutime, cstime)."""
    f = ["S", str(ppid)] + ["0"] * 9 + [str(t) for t in ticks] + ["20", "0", "1", "0", str(start)] + ["0"] * 30
    return f"{pid} ({comm}) " + " ".join(f) + "\n"


def _fake_proc(root, cpu_rows, procs):
    """A fake /proc: ``cpu_rows`` {n: 8 counters}, ``procs`` {pid: (comm, ppid, start, 4 ticks)}."""
    root.mkdir(parents=True)
    total = [sum(r[i] for r in cpu_rows.values()) for i in range(8)]
    lines = ["cpu  " + " ".join(map(str, total + [0, 0]))]
    lines += [f"cpu{n} " + " ".join(map(str, row + [0, 0])) for n, row in sorted(cpu_rows.items())]
    lines += ["intr 12345 0 0", "ctxt 999", "procs_running 3"]
    (root / "stat").write_text("\n".join(lines) + "\n")
    for pid, (comm, ppid, start, ticks) in procs.items():
        (root / str(pid)).mkdir()
        (root / str(pid) / "stat").write_text(_stat_line(pid, comm, ppid, start, ticks))
    (root / "self").mkdir()  # not a pid: ignored
    return root


def _naive_outside(a_cpu, b_cpu, a_procs, b_procs, cpus, fwk_pids):
    """Busy ticks of ``cpus`` between the two states, less the fwk processes' and their
    descendants', per tick of wall time; clamped to [0, len(cpus)]."""
    def busy(rows):
        return sum(r[0] + r[1] + r[2] + r[5] + r[6] + r[7] for n, r in rows.items() if n in cpus)

    def total(rows):
        return sum(sum(r) for n, r in rows.items() if n in cpus)

    def family(ps):
        fam = {p for p in fwk_pids if p in ps}
        grew = True
        while grew:
            new = {p for p, v in ps.items() if v[1] in fam} - fam
            fam |= new
            grew = bool(new)
        return {(p, ps[p][2]): sum(ps[p][3]) for p in fam}

    fa, fb = family(a_procs), family(b_procs)
    fwk = sum(t - fa.get(k, 0) for k, t in fb.items())
    elapsed = (total(b_cpu) - total(a_cpu)) / len(cpus)
    return min(len(cpus), max(0.0, (busy(b_cpu) - busy(a_cpu) - fwk) / elapsed))


def test_the_measured_outside_load_against_a_naive_reference(tmp_path):
    import random

    rnd = random.Random(1)
    seen = []
    for case in range(60):
        ncpu = rnd.randint(1, 6)
        cpus = set(rnd.sample(range(ncpu), rnd.randint(1, ncpu)))
        a_cpu = {n: [rnd.randint(0, 10**6) for _ in range(8)] for n in range(ncpu)}
        wall = rnd.randint(20, 500)  # ticks per CPU between the states
        b_cpu = {}
        for n, row in a_cpu.items():
            busy = rnd.randint(0, wall)
            split = [rnd.random() for _ in range(8)]
            split[3] = split[4] = 0  # busy time goes to the busy fields only
            s = sum(split)
            add = [int(busy * x / s) for x in split]
            add[3] = wall - sum(add)  # the rest idle
            b_cpu[n] = [v + d for v, d in zip(row, add)]
        me, other, child, grandchild, stranger = 100, 200, 300, 400, 500
        a_procs = {me: ("python", 1, 50, (10, 5, 0, 0)), other: ("fwk (a) b", 1, 60, (20, 5, 1, 1)),
                   child: ("pt_data_worker", me, 70, (3, 1, 0, 0)), stranger: ("make", 1, 80, (9, 9, 9, 9))}
        grow = lambda t: tuple(v + rnd.randint(0, wall // 8) for v in t)  # noqa: E731
        b_procs = {p: (c, pp, st, grow(t)) for p, (c, pp, st, t) in a_procs.items()}
        if case % 3 == 0:
            b_procs[grandchild] = ("worker", child, 90, (rnd.randint(0, 20), 0, 0, 0))  # appeared in the window
        if case % 4 == 0:
            del b_procs[other]  # an fwk process that ended
        fwk = {me, other}
        a = threads.snapshot(fwk, cpus, proc=_fake_proc(tmp_path / f"a{case}", a_cpu, a_procs))
        b = threads.snapshot(fwk, cpus, proc=_fake_proc(tmp_path / f"b{case}", b_cpu, b_procs))
        assert a.cpus == tuple(sorted(cpus))
        got = threads.outside_between(a, b)
        want = _naive_outside(a_cpu, b_cpu, a_procs, b_procs, cpus, fwk)
        assert got == pytest.approx(want, abs=1e-9), case
        seen.append(got)
    assert min(seen) < 0.5 * max(seen) and 0 < max(seen)  # the cases span a range of loads


@pytest.fixture
def real_load():
    """This test measures (a fake /proc, or the machine): ``no_outside_load`` stays out."""


def test_outside_load_measures_from_the_previous_call(real_load, tmp_path, monkeypatch):
    monkeypatch.setattr(threads, "MIN_WINDOW", 0.0)
    monkeypatch.setattr(threads, "_affinity", lambda: {0, 1})
    monkeypatch.setattr(threads._LOAD, "last", None)
    idle = [0, 0, 0, 1000, 0, 0, 0, 0]
    busy = [300, 0, 90, 1010, 0, 0, 0, 10]  # cpu0: 400 ticks busy of 410
    half = [100, 0, 0, 1310, 0, 0, 0, 0]  # cpu1: 100 ticks busy of 410
    p0 = _fake_proc(tmp_path / "t0", {0: idle, 1: idle}, {os.getpid(): ("python", 1, 5, (0, 0, 0, 0))})
    p1 = _fake_proc(tmp_path / "t1", {0: busy, 1: half}, {os.getpid(): ("python", 1, 5, (41, 0, 0, 0))})
    assert threads.outside_load({os.getpid()}, proc=p0) == (0.0, 2)  # the first window: no time passed
    out, cpus = threads.outside_load({os.getpid()}, proc=p1)  # (500 busy - 41 this process's) / 410
    assert cpus == 2 and out == pytest.approx(459 / 410)
    assert threads.outside_load({os.getpid()}, proc=tmp_path / "missing") == (0.0, 2)  # unreadable: no load


def test_outside_load_on_this_machine_is_a_number_of_cpus(real_load):
    out, cpus = threads.outside_load()
    assert cpus >= 1 and 0.0 <= out <= cpus


# ---- idle threads wait passively (fwk._waiting) ----------------------------------------------------

WAIT_VARS = ("OMP_WAIT_POLICY", "OPENBLAS_THREAD_TIMEOUT", "GOTO_THREAD_TIMEOUT", "GOMP_SPINCOUNT")


def _child_env(**set_):
    env = {k: v for k, v in os.environ.items() if k not in WAIT_VARS}
    env.update(set_)
    return env


def _env_after(code, **set_):
    out = subprocess.run([sys.executable, "-c", code + "; import os, json; print(json.dumps("
                          "{k: os.environ.get(k) for k in %r}))" % (WAIT_VARS,)],
                         env=_child_env(**set_), capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("entry", ["import fwk", "from fwk.cli import main",  # the console script's import
                                   "import fwk.engine.distributed", "import fwk.rank"])  # DDP ranks: python -m fwk.rank
def test_every_entry_point_sets_the_wait_policy(entry):
    got = _env_after(entry)
    assert got["OMP_WAIT_POLICY"] == "PASSIVE" and got["OPENBLAS_THREAD_TIMEOUT"] == "4"


def test_the_users_own_settings_win():
    assert _env_after("import fwk", OMP_WAIT_POLICY="active") == {
        "OMP_WAIT_POLICY": "active", "OPENBLAS_THREAD_TIMEOUT": None, "GOTO_THREAD_TIMEOUT": None,
        "GOMP_SPINCOUNT": None}  # the user chose how threads wait: fwk adds nothing
    got = _env_after("import fwk", OPENBLAS_THREAD_TIMEOUT="28")
    assert got["OPENBLAS_THREAD_TIMEOUT"] == "28" and got["OMP_WAIT_POLICY"] == "PASSIVE"
    got = _env_after("import fwk", GOTO_THREAD_TIMEOUT="20")
    assert got["OPENBLAS_THREAD_TIMEOUT"] is None and got["OMP_WAIT_POLICY"] == "PASSIVE"
    got = _env_after("import fwk", OMP_WAIT_POLICY="PASSIVE", GOMP_SPINCOUNT="1000")
    assert got["GOMP_SPINCOUNT"] == "1000" and got["OPENBLAS_THREAD_TIMEOUT"] == "4"


def test_apply_records_what_it_set_and_what_was_loaded_before():
    from fwk import _waiting

    env = {"OPENBLAS_THREAD_TIMEOUT": "10"}
    assert _waiting.apply(env, {}) == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert env == {"OPENBLAS_THREAD_TIMEOUT": "10", "OMP_WAIT_POLICY": "PASSIVE"}
    assert _waiting.apply(env, {}) == {}  # idempotent
    code = ("import numpy, fwk; from fwk import _waiting; "
            "print(sorted(_waiting.added), _waiting.loaded_before)")
    out = subprocess.run([sys.executable, "-c", code], env=_child_env(), capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[0] == "['OMP_WAIT_POLICY', 'OPENBLAS_THREAD_TIMEOUT'] ['numpy']"




@pytest.mark.parametrize("lib", ["torch", "numpy"])
def test_idle_pools_do_not_spin(lib):
    """The policy takes effect: a process whose pools (torch's OpenMP, NumPy's OpenBLAS; 2 threads)
    sit idle between products burns almost no CPU while it sleeps. Spinning threads burn 0.4-0.7
    of a core here; a loaded machine can only lower the figure, never raise it."""
    from tests.core.scripts import load_benchmark

    # benchmarks/load.py's probe (the same child script the benchmark prints), with fwk imported first
    assert load_benchmark("load").probe_idle_cpu(lib, _child_env()) < 0.15
