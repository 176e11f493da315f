"""How many threads a fwk process computes with: the cores left free by other work, shared by
the live fwk processes.

Two trainings that each run one OpenMP thread per core on the same cores oversubscribe them:
the threads of one process spin at barriers while the other's hold the core, and both slow
down far beyond the 2x that sharing costs (PBS's fit of ``recipes/pbs_face_compression.yaml
train.epochs=4`` on 2 cores: 41 s alone, 115-117 s each for two at once). The same holds beside
any other compute job. So every fwk process that computes registers itself, and uses

    threads = max(1, free // live)
    free    = min(cores, cpus - round(outside))

where ``cores`` are the cores this process may run on (its CPU affinity, capped by a cgroup
CPU quota), ``cpus`` the CPUs of its affinity, ``outside`` how many of those CPUs were busy with
work other than fwk's (below), rounded to the nearest whole CPU (half up), and ``live`` the
registered fwk processes (this one included). With nothing else running this is
``max(1, cores // live)``; beside a 2-thread compute job on 2 cores, 1 thread.

``outside`` (``outside_load``) is measured from ``/proc/stat``: the busy time (user, nice,
system, irq, softirq, steal) of the CPUs of this process's affinity over a window, less the CPU
time the live registered fwk processes and their descendants (data-loader workers) used in the
same window, divided by the window's length; clamped to [0, cpus]. The window runs from the
previous measurement (the first is taken when the process registers) to now, and is at least
``MIN_WINDOW`` (0.2 s; a call sooner than that sleeps the rest). An fwk process that appeared
during the window counts as fwk for its whole life (so ``outside`` errs low: towards the rule
without load). Where ``/proc`` cannot be read, ``outside`` is 0.

**A run's count is fixed when it starts.** ``fwk run`` (``fwk.runs.execute``) applies the rule
once, as the run starts, and pins the result for the rest of the run (``pin``): every training
of the run uses it, whatever starts or ends beside it, because thread counts change the order of
floating-point reductions and so the numbers (a fresh clone's main job moved mouth-wide metrics
by 7-12 % between a 1-thread and a 2-thread run of one seed). The count is printed, recorded in
``versions.json`` (``threads``, ``threads_why``) and the report, and ``fwk run --resume`` reuses
it. The spread of a result is measured with seeds (``seeds:``), never with thread counts.
Outside a run (``fit`` called from Python, the benchmarks) nothing is pinned: ``fit`` applies the
rule when it starts and again at the start of every epoch (the window then being the epoch just
run), so a training that started alone gives up threads when a second one or another job starts,
and takes them back when it ends.

An explicit count wins: ``FWK_THREADS=n`` (``fwk --threads n``); then an allocation an executor
made for this process, ``FWK_ALLOCATED_CPUS=n`` (a grid member running as a Ray task sets it to
the CPUs Ray reserved for it; the ranks of a DDP training launched by fwk split it among
themselves), which replaces the rule: the executor already shares the cores;
then ``OMP_NUM_THREADS`` (Ray sets it in its workers as well, which is why the allocation comes
first).

Registrations are small files ``<pid>`` (holding the pid and the process's start time, so a
reused pid is not mistaken for it) in a per-user folder: ``$FWK_RUNTIME_DIR``, else
``$XDG_RUNTIME_DIR/fwk/procs``, else ``<tmp>/fwk-<uid>/procs``. A process removes its file on
exit; files of processes that died without doing so are ignored and removed by whoever counts.

The intra-op pool is sized (``torch.set_num_threads``), and so are the BLAS pools that NumPy
and SciPy use (OpenBLAS, MKL; through ``threadpoolctl``), whose matrix products in the metrics,
the spectral assembly and the dr solves would otherwise still take every core. Eager-mode
training does not use torch's inter-op pool, which torch creates lazily and lets a process
size only once. How idle threads wait (passively: they sleep instead of spinning) is set on
``import fwk``, before torch and NumPy load (``fwk._waiting``).

A run is bit-for-bit reproducible (and resumable to the same weights) for its count; ``fwk run
--threads N`` (``FWK_THREADS``) reproduces a run that recorded N. This module imports neither
torch nor Lightning.
"""
from __future__ import annotations

import atexit
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from threadpoolctl import threadpool_limits

from ..errors import FwkError

ENV_THREADS = "FWK_THREADS"
ENV_ALLOCATED = "FWK_ALLOCATED_CPUS"
ENV_RUNTIME_DIR = "FWK_RUNTIME_DIR"

#: the shortest window over which ``outside_load`` measures (seconds)
MIN_WINDOW = 0.2
PROC = Path("/proc")

_registered: dict[Path, str] = {}  # registration file -> its content, for this process


def runtime_dir() -> Path:
    """The folder of the registrations (not created)."""
    override = os.environ.get(ENV_RUNTIME_DIR)
    if override:
        return Path(override)
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg and os.path.isdir(xdg) and os.access(xdg, os.W_OK):
        return Path(xdg) / "fwk" / "procs"
    return Path(tempfile.gettempdir()) / f"fwk-{os.getuid()}" / "procs"


def _own_dir(directory: Path) -> bool:
    """Create ``directory`` (mode 0700) and check it and its parent belong to this user."""
    try:
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        uid = os.getuid()
        return all(p.stat().st_uid == uid for p in (directory, directory.parent))
    except OSError:
        return False


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, start time in clock ticks since boot) of ``pid`` from /proc, None where unreadable."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) "; comm may hold spaces
    try:
        return fields[0], int(fields[19])
    except (IndexError, ValueError):
        return None


def _identity(pid: int) -> str:
    st = _stat(pid)
    return f"{pid} {st[1] if st else '-'}\n"


def _alive(pid: int, start: str) -> bool:
    """Whether the process that registered as (pid, start) still runs."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # exists, another user's (cannot happen in a per-user folder, but harmless)
    except OSError:
        return False
    st = _stat(pid)
    if st is None:
        return True  # no /proc: the signal test is all there is
    state, now = st
    return state not in ("Z", "X") and (start == "-" or str(now) == start)


def register(directory: Path | None = None) -> Path | None:
    """Register this process (idempotent; the file is removed at exit). Returns the file, or
    None where the folder cannot be used (then this process counts only itself)."""
    directory = Path(directory) if directory is not None else runtime_dir()
    path = directory / str(os.getpid())
    if path in _registered and path.exists():
        return path
    if not _own_dir(directory):
        return None
    content = _identity(os.getpid())
    tmp = directory / f".{os.getpid()}.tmp"
    try:
        tmp.write_text(content)
        os.replace(tmp, path)
    except OSError:
        return None
    if not _registered:
        atexit.register(unregister)
    _registered[path] = content
    if _LOAD.last is None:
        _LOAD.last = snapshot(live_processes(directory))  # the first window of outside_load starts here
    return path


def unregister() -> None:
    """Remove this process's registrations (those it wrote, still holding its identity)."""
    for path, content in list(_registered.items()):
        try:
            if path.read_text() == content:
                path.unlink()
        except OSError:
            pass
        _registered.pop(path, None)


def live_processes(directory: Path | None = None) -> list[int]:
    """The pids of the live registered processes; files of dead ones (and unreadable ones) are
    removed."""
    directory = Path(directory) if directory is not None else runtime_dir()
    try:
        entries = list(directory.iterdir())
    except OSError:
        return []
    pids = []
    for p in entries:
        if not p.name.isdigit():
            continue
        try:
            pid_s, start = p.read_text().split()
            pid = int(pid_s)
        except (OSError, ValueError):
            pid, start = -1, "-"
        if pid == int(p.name) and _alive(pid, start):
            pids.append(pid)
        else:
            try:
                p.unlink()
            except OSError:
                pass
    return sorted(pids)


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity, capped by a cgroup v2 CPU quota."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            n = min(n, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, n)


# ---- the load of the machine -------------------------------------------------------------------

#: /proc/stat fields (after "cpuN") that count as busy: user nice system idle iowait irq softirq
#: steal (guest time is included in user); idle and iowait are not busy
_BUSY = (0, 1, 2, 5, 6, 7)


@dataclass(frozen=True)
class LoadSnapshot:
    """The CPU counters at one moment: ``busy`` and ``total`` clock ticks summed over the CPUs
    ``cpus``, and ``fwk`` the CPU ticks (own and reaped children's) of each fwk process and live
    descendant, keyed by (pid, start time)."""
    cpus: tuple[int, ...]
    busy: int
    total: int
    fwk: dict = field(default_factory=dict)
    at: float = 0.0  # time.monotonic() when taken


def _cpu_ticks(cpus, proc: Path) -> tuple[tuple[int, ...], int, int] | None:
    """(CPUs found, busy ticks, total ticks) of the ``cpuN`` lines of ``proc/stat`` for N in ``cpus``."""
    try:
        text = (proc / "stat").read_text()
    except OSError:
        return None
    found, busy, total = [], 0, 0
    for line in text.splitlines():
        name, _, rest = line.partition(" ")
        if not name.startswith("cpu") or name == "cpu":
            continue
        try:
            n = int(name[3:])
            values = [int(v) for v in rest.split()[:8]]
        except ValueError:
            continue
        if n in cpus and len(values) >= 4:
            values += [0] * (8 - len(values))
            found.append(n)
            busy += sum(values[i] for i in _BUSY)
            total += sum(values)
    return (tuple(found), busy, total) if found else None


def _proc_stat(path: Path) -> tuple[int, int, int, int] | None:
    """(pid, ppid, start, CPU ticks: utime + stime + cutime + cstime) from a ``/proc/<pid>/stat``."""
    try:
        text = path.read_text()
        f = text[text.rindex(")") + 2:].split()
        return int(text.split(" ", 1)[0]), int(f[1]), int(f[19]), sum(int(v) for v in f[11:15])
    except (OSError, ValueError, IndexError):
        return None


def _fwk_ticks(pids, proc: Path) -> dict:
    """CPU ticks of the processes ``pids`` and of their live descendants, by (pid, start)."""
    if not pids:
        return {}
    stats = {}
    try:
        entries = [p for p in proc.iterdir() if p.name.isdigit()]
    except OSError:
        entries = [proc / str(p) for p in pids]
    for d in entries:
        st = _proc_stat(d / "stat")
        if st is not None:
            stats[st[0]] = st
    children: dict[int, list[int]] = {}
    for pid, ppid, _, _ in stats.values():
        children.setdefault(ppid, []).append(pid)
    out, todo, seen = {}, [p for p in pids if p in stats], set()
    while todo:
        pid = todo.pop()
        if pid in seen:
            continue
        seen.add(pid)
        _, _, start, ticks = stats[pid]
        out[(pid, start)] = ticks
        todo.extend(children.get(pid, ()))
    return out


def _affinity() -> set[int]:
    try:
        return set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return set(range(os.cpu_count() or 1))


def snapshot(fwk_pids=(), cpus=None, proc: Path | None = None) -> LoadSnapshot | None:
    """The CPU counters now (None where ``proc/stat`` cannot be read): the CPUs ``cpus``
    (default: this process's affinity), and the fwk processes ``fwk_pids`` with their descendants."""
    proc = PROC if proc is None else Path(proc)
    cpu = _cpu_ticks(_affinity() if cpus is None else set(cpus), proc)
    if cpu is None:
        return None
    return LoadSnapshot(cpu[0], cpu[1], cpu[2], _fwk_ticks(set(fwk_pids), proc), time.monotonic())


def outside_between(a: LoadSnapshot | None, b: LoadSnapshot | None) -> float | None:
    """How many CPUs of ``b.cpus`` were busy, on average from ``a`` to ``b``, with work other than
    the fwk processes' of ``b`` (a process of ``b`` not in ``a`` counts with all its ticks);
    clamped to [0, len(cpus)]. None where the snapshots do not compare (missing, other CPUs,
    no time between them)."""
    if a is None or b is None or a.cpus != b.cpus or b.total <= a.total:
        return None
    elapsed = (b.total - a.total) / len(b.cpus)  # ticks of wall time
    fwk = sum(t - a.fwk.get(k, 0) for k, t in b.fwk.items())
    return min(float(len(b.cpus)), max(0.0, (b.busy - a.busy - fwk) / elapsed))


class _LoadState:
    last: LoadSnapshot | None = None
    pinned: tuple[int, str] | None = None  # (threads, why) fixed for the run in progress


_LOAD = _LoadState()


#: log -> the thread counts reported through it (``report_threads``)
_threads_reported: dict = {}


def report_threads(log, n: int, why: str, key=None) -> bool:
    """Say ``threads: n (why)`` through ``log`` unless this count was said for ``key`` (the run's
    log file; default ``log`` itself) before: a count that flips between two values as other fwk
    processes start and end (every epoch of a long run beside a short one), or that every model
    of a run finds again, is said once per value, not at every flip or fit. Returns whether it
    was said."""
    said = _threads_reported.setdefault(log if key is None else key, set())
    if n in said:
        return False
    said.add(n)
    log(f"threads: {n} ({why})")
    return True


def forget_reported(key) -> None:
    """Let ``report_threads`` say every count for ``key`` again (a run's log as the run starts or
    resumes)."""
    _threads_reported.pop(key, None)


def recorded_threads(run_dir) -> tuple[int, str] | None:
    """(threads, why) that a run's ``versions.json`` recorded when it started (``fwk.runs.fix_threads``),
    or None (no such record: an earlier version's run, a folder that is not a run, an unreadable or
    implausible one)."""
    try:
        stored = json.loads((Path(run_dir) / "versions.json").read_text())
    except (OSError, ValueError):
        return None
    n = stored.get("threads") if isinstance(stored, dict) else None
    if isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= 4096:
        why = stored.get("threads_why")
        return n, why if isinstance(why, str) and why else "recorded in versions.json"
    return None


def pin(threads: int, why: str) -> None:
    """Fix this process's count at ``threads`` until ``unpin``: ``thread_budget`` then returns it in
    place of the load rule (an explicit ``FWK_THREADS``, an executor's allocation and
    ``OMP_NUM_THREADS`` still come first). ``fwk.runs.execute`` pins a run's count as it starts."""
    if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
        raise FwkError(f"threads: expected a whole number >= 1, got {threads!r}")
    _LOAD.pinned = (threads, why)


def unpin() -> None:
    """Let the load rule decide again (``pin``)."""
    _LOAD.pinned = None


def pinned() -> tuple[int, str] | None:
    """(threads, why) pinned for the run in progress, or None."""
    return _LOAD.pinned


def outside_load(pids=None, directory: Path | None = None, proc: Path | None = None) -> tuple[float, int]:
    """(outside, cpus): the CPUs of this process's affinity busy with work other than fwk's since
    the previous call (or registration), over at least ``MIN_WINDOW`` seconds, and how many
    CPUs that counts; (0.0, cpus) where it cannot be measured. ``pids``: the fwk processes
    (default: the live registered ones and this one). See the module docstring."""
    if pids is None:
        pids = set(live_processes(directory)) | {os.getpid()}
    last = _LOAD.last if _LOAD.last is not None else snapshot(pids, proc=proc)
    if last is not None:
        wait = MIN_WINDOW - (time.monotonic() - last.at)
        if wait > 0:
            time.sleep(wait)
    now = snapshot(pids, proc=proc)
    if now is not None:
        _LOAD.last = now
    outside = outside_between(last, now)
    cpus = len(now.cpus) if now is not None else len(_affinity())
    return (outside if outside is not None else 0.0), cpus


def share(cores: int, live: int, outside: float = 0.0, cpus: int | None = None) -> int:
    """The rule: ``max(1, min(cores, cpus - round(outside)) // live)``, ``outside`` rounded half up."""
    cpus = cores if cpus is None else cpus
    free = min(cores, cpus - math.floor(outside + 0.5))
    return max(1, free // max(1, live))


def _explicit(env, key: str, strict: bool) -> int | None:
    value = (env.get(key) or "").strip()
    if not value or value == "auto":
        return None
    try:
        n = int(value.split(",")[0])  # OpenMP allows a list per nesting level
    except ValueError:
        n = 0
    if n < 1:
        if strict:
            raise FwkError(f"{key}={value!r}: expected a number of threads >= 1 (or auto)")
        return None
    return n


def explicit_threads(env=None) -> tuple[int, str] | None:
    """(threads, why) where the environment gives the count (``FWK_THREADS``, an executor's
    ``FWK_ALLOCATED_CPUS``, ``OMP_NUM_THREADS``, in that order), else None."""
    env = os.environ if env is None else env
    for key, strict in ((ENV_THREADS, True), (ENV_ALLOCATED, True), ("OMP_NUM_THREADS", False)):
        n = _explicit(env, key, strict)
        if n is not None:
            if key == ENV_ALLOCATED:
                return n, f"{n} CPU{'s' if n > 1 else ''} allocated to this process"
            return n, f"{key}={n}"
    return None


def thread_budget(env=None, cores: int | None = None, live: int | None = None,
                  directory: Path | None = None, outside: float | None = None,
                  cpus: int | None = None) -> tuple[int, str]:
    """(threads, why): ``FWK_THREADS``, else ``FWK_ALLOCATED_CPUS`` (an executor's allocation),
    else ``OMP_NUM_THREADS`` (where set), else the count pinned for the run in progress (``pin``),
    else ``share(cores, live, outside, cpus)``: ``live`` the
    live registered fwk processes, this one counted whether registered or not; ``outside`` the
    CPUs busy with other work and ``cpus`` the CPUs that counts (``outside_load()`` where not
    given; ``cpus`` defaults to ``cores`` when ``outside`` is given)."""
    given = explicit_threads(env)
    if given is not None:
        return given
    if _LOAD.pinned is not None:
        return _LOAD.pinned
    cores = cores if cores is not None else available_cores()
    pids = None
    if live is None:
        pids = set(live_processes(directory)) | {os.getpid()}
        live = len(pids)
    live = max(1, live)
    if outside is None:
        outside, measured = outside_load(pids, directory)
        cpus = measured if cpus is None else cpus
    cpus = cores if cpus is None else cpus
    n = share(cores, live, outside, cpus)
    why = f"{live} fwk process{'es' if live > 1 else ''} on {cores} core{'s' if cores > 1 else ''}"
    taken = math.floor(outside + 0.5)
    if taken > 0:
        why += f", {outside:.1f} of {cpus} CPU{'s' if cpus > 1 else ''} busy with other work"
    return n, why


def apply_threads(env=None, directory: Path | None = None) -> tuple[int, str, bool]:
    """Set torch's intra-op threads to ``thread_budget``: (threads, why, changed)."""
    import torch  # deferred: ~1 s of import time; the callers have imported it already

    n, why = thread_budget(env, directory=directory)
    changed = torch.get_num_threads() != n
    if changed:
        torch.set_num_threads(n)
        threadpool_limits(limits=n, user_api="blas")
    return n, why, changed
