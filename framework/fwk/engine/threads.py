"""How many threads a fwk process computes with: the cores shared by the live fwk processes.

Two trainings that each run one OpenMP thread per core on the same cores oversubscribe them:
the threads of one process spin at barriers while the other's hold the core, and both slow
down far beyond the 2x that sharing costs (PBS's fit of ``recipes/pbs_face_compression.yaml
train.epochs=4`` on 2 cores: 41 s alone, 115-117 s each for two at once). So every fwk
process that computes registers itself, and uses

    threads = max(1, cores // live fwk processes)

where ``cores`` are the cores this process may run on (its CPU affinity, capped by a cgroup
CPU quota) and the live processes are those registered (this one included). ``fit`` applies
the rule when it starts and again at the start of every epoch, so a training that started
alone gives up threads when a second one starts, and takes them back when it ends.

An explicit count wins: ``FWK_THREADS=n`` (``fwk --threads n``); then an allocation an executor
made for this process, ``FWK_ALLOCATED_CPUS=n`` (a grid member running as a Ray task sets it to
the CPUs Ray reserved for it; the ranks of a DDP training launched by fwk split it among
themselves), which replaces the count of live processes: the executor already shares the cores;
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
size only once.

Thread counts change the order of some floating-point reductions: a run is bit-for-bit
reproducible (and resumable to the same weights) for a fixed count, so pin it with
``FWK_THREADS`` where that matters. This module imports neither torch nor Lightning.
"""
from __future__ import annotations

import atexit
import math
import os
import tempfile
from pathlib import Path

from threadpoolctl import threadpool_limits

from ..errors import FwkError

ENV_THREADS = "FWK_THREADS"
ENV_ALLOCATED = "FWK_ALLOCATED_CPUS"
ENV_RUNTIME_DIR = "FWK_RUNTIME_DIR"

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


def thread_budget(env=None, cores: int | None = None, live: int | None = None,
                  directory: Path | None = None) -> tuple[int, str]:
    """(threads, why): ``FWK_THREADS``, else ``FWK_ALLOCATED_CPUS`` (an executor's allocation),
    else ``OMP_NUM_THREADS`` (where set), else ``max(1, cores // live)`` with ``live`` the live
    registered fwk processes, this one counted whether registered or not."""
    env = os.environ if env is None else env
    for key, strict in ((ENV_THREADS, True), (ENV_ALLOCATED, True), ("OMP_NUM_THREADS", False)):
        n = _explicit(env, key, strict)
        if n is not None:
            if key == ENV_ALLOCATED:
                return n, f"{n} CPU{'s' if n > 1 else ''} allocated to this process"
            return n, f"{key}={n}"
    cores = cores if cores is not None else available_cores()
    if live is None:
        live = len(set(live_processes(directory)) | {os.getpid()})
    live = max(1, live)
    return max(1, cores // live), f"{live} fwk process{'es' if live > 1 else ''} on {cores} core{'s' if cores > 1 else ''}"


def apply_threads(env=None, directory: Path | None = None) -> tuple[int, str, bool]:
    """Set torch's intra-op threads to ``thread_budget``: (threads, why, changed)."""
    import torch  # deferred: ~1 s of import time; the callers have imported it already

    n, why = thread_budget(env, directory=directory)
    changed = torch.get_num_threads() != n
    if changed:
        torch.set_num_threads(n)
        threadpool_limits(limits=n, user_api="blas")
    return n, why, changed
