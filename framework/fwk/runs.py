"""Run directories and the run context every task and model receives.

``fwk run recipes/x.yaml`` writes ``runs/<name>-<UTC yyyymmdd-HHMMSS>/`` (or under
``--runs-dir`` / ``FWK_RUNS_DIR``), never overwriting; every file is written atomically, with the
mode the process umask gives new files. The output folders (the runs folder, ``$FWK_CACHE``)
are checked before anything is written (``fwk.paths.check_dir``).

A run directory is complete, or says why not:

- while a process writes it, it holds ``RUNNING`` (its pid, host and start), locked with
  ``flock``: a second ``fwk run --resume`` of the same directory is refused while the first
  lives, and a reader tells a live run (locked) from a killed one (``RUNNING``, unlocked);
- an exception of any kind (a bug, Ctrl-C, SIGTERM, a full disk) replaces ``RUNNING`` by
  ``FAILED``: the error's line, its traceback and the command that resumes (``kill -9``
  cannot be caught: it leaves ``RUNNING``);
- on success neither is left. ``run_state(run_dir)`` reads this; ``fwk report`` and
  ``fwk.lifecycle.open_run`` refuse a run that is not complete.

A user's mistake found while validating writes no run directory; one found while running (a
bad mesh file, say) removes the directory this invocation created, and its one-line message says
so, unless it already holds a trained model or a checkpoint (then it is marked ``FAILED`` and
the message gives the ``--resume`` command that continues it).
"""
from __future__ import annotations

import copy
import datetime as _dt
import fcntl
import hashlib
import io
import json
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import threading
import traceback
from pathlib import Path
from typing import Iterable

import numpy as np
import yaml
from tqdm.auto import tqdm

from . import __version__
from .cache import Cache, atomic_write_bytes, file_mode
from .engine.config import TrainConfig
from .engine.threads import (explicit_threads, forget_reported, pin, pinned, recorded_threads, register, report_threads,
                             thread_budget, unpin)
from .errors import FwkError, PathError, RecipeError, Terminated
from .paths import check_dir
from .plugins import get_registry
from .recipes import Spec, load_recipe, make_spec, read_recipe_file, resolve, to_plain
from .registry import Registry
from .safeio import refuse_pickled
from .forked import LOG_PREFIX, ONE_AFTER_ANOTHER, SEEDS_ONE_AFTER_ANOTHER
from .seeds import fans_out_seeds, run_seeds

SCOPED = ("checkpoints", "tb", "curves")  # per network, under the model's label
#: versions.json's mark of a run started by an fwk that fits models side by side (fwk.sidebyside)
SIDE_BY_SIDE = "side_by_side"
#: versions.json's mark of a run started by an fwk that runs a recipe's seeds side by side (fwk.seeds)
SEEDS_SIDE_BY_SIDE = "seeds_side_by_side"


def _default_device() -> str:
    """``cuda`` when available, else ``cpu``."""
    # deferred: torch costs ~1 s of import time (measured with python -X importtime) that
    # `fwk --help` and `fwk report`, which load this module, need not pay
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _check_cuda() -> None:
    """``--device cuda`` asked for where torch sees no CUDA device: one line, before any work
    (Lightning's ``auto`` accelerator would otherwise train on the CPU without a word)."""
    import torch

    if not torch.cuda.is_available():
        build = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise FwkError(f"--device cuda: torch {torch.__version__} ({build}) sees no CUDA device here; "
                       "run with --device cpu (or without --device), or install a CUDA build of torch")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return to_plain(o)


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as indented JSON (NumPy values, paths, specs and dataclasses converted),
    atomically."""
    atomic_write_bytes(Path(path), (json.dumps(obj, indent=2, default=_json_default, allow_nan=True) + "\n").encode())


class RunContext:
    """Where a run writes, and the shared services it uses (see COMMON contract in docs)."""

    def __init__(self, run_dir: Path, registry: Registry, cache: Cache | None = None, seed: int = 0,
                 recipe: dict | None = None, train=None, device: str | None = None, quiet: bool = False,
                 resume: bool = False, scope: str | None = None, log_file: Path | None = None):
        self.run_dir = Path(run_dir)
        self.registry = registry
        self.cache = cache or Cache()
        self.seed = int(seed)
        self.recipe = recipe or {}
        self.train = train if train is not None else TrainConfig()
        self.device = device if device is not None else _default_device()
        self.quiet = quiet
        self.resume = resume
        self.scope = scope
        self.source: str | None = None  # the recipe file, for paths relative to it
        self.log_file = log_file if log_file is not None else self.run_dir / "log.txt"

    # files -------------------------------------------------------------------------
    def path(self, *parts) -> Path:
        """``run_dir/parts...`` (checkpoints and TensorBoard events under the scope), its folder
        created."""
        parts = [str(p) for p in parts]
        if self.scope and parts and parts[0] in SCOPED:
            parts = [parts[0], self.scope, *parts[1:]]
        p = self.run_dir.joinpath(*parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_json(self, rel, obj) -> Path:
        """Write ``obj`` as JSON to ``rel`` in the run directory (atomic); returns the path."""
        p = self.path(rel)
        write_json(p, obj)
        return p

    def write_text(self, rel, text: str) -> Path:
        """Write ``text`` to ``rel`` in the run directory (atomic); returns the path."""
        p = self.path(rel)
        atomic_write_bytes(p, text.encode())
        return p

    def save_npz(self, rel, **arrays) -> Path:
        """Save ``arrays`` as an .npz file at ``rel`` in the run directory (atomic); returns the
        path."""
        p = self.path(rel)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write_bytes(p, buf.getvalue())
        return p

    # output ------------------------------------------------------------------------
    def log(self, msg: str) -> None:
        """Print ``msg`` (unless quiet) and append it to the run's log file (after the process's
        ``LOG_PREFIX``: a grid member's name while members run side by side, ``fwk.sidebyside``)."""
        if not self.quiet:
            print(msg, flush=True)
        try:
            self.log_file.parent.mkdir(parents=True, exist_ok=True)
            with open(self.log_file, "a") as f:
                f.write(LOG_PREFIX[0] + msg.rstrip("\n") + "\n")
        except OSError:
            pass

    def progress(self, iterable: Iterable, desc: str = "", total: int | None = None, **kw):
        """A progress bar over ``iterable``, shown on a terminal unless quiet."""
        disable = self.quiet or not sys.stderr.isatty()
        return tqdm(iterable, desc=desc, total=total, disable=disable, leave=False, dynamic_ncols=True, **kw)

    # components --------------------------------------------------------------------
    def build(self, kind: str, spec, *args, **extra):
        """Build a component of ``kind`` from a Spec, a name or a mapping with ``name``; ``args``
        and ``extra`` go to its constructor."""
        if not isinstance(spec, Spec):
            spec = make_spec(kind, spec, kind, self.registry)
        return spec.build(*args, **extra)

    def child(self, name: str) -> "RunContext":
        """A context for a sub-run in ``run_dir/name`` (its own files and scope, the same log)."""
        c = copy.copy(self)
        c.run_dir = self.run_dir / name
        c.log_file = self.log_file  # one log for the whole run
        c.scope = None
        c.run_dir.mkdir(parents=True, exist_ok=True)
        return c

    def scoped(self, label: str) -> "RunContext":
        """The same run; checkpoints and TensorBoard events go under ``<kind>/<label>/``."""
        c = copy.copy(self)
        c.scope = f"{self.scope}/{label}" if self.scope else label
        return c


def make_test_context(tmp_path, seed: int = 0, registry: Registry | None = None, **train_overrides) -> RunContext:
    """A real RunContext for tests: quiet, CPU, its own cache under tmp_path."""
    train = TrainConfig(**train_overrides) if train_overrides else TrainConfig(epochs=2, batch_size=8)
    tmp_path = Path(tmp_path)
    return RunContext(tmp_path / "run", registry or get_registry(), Cache(tmp_path / "cache"), seed=seed,
                      train=train, device="cpu", quiet=True)


# ----------------------------------------------------------------------------- run dirs

def runs_root(runs_dir: str | None = None) -> Path:
    """Where run directories go: ``runs_dir``, else ``$FWK_RUNS_DIR``, else ``./runs``."""
    return Path(runs_dir or os.environ.get("FWK_RUNS_DIR") or "runs").expanduser()


def check_runs_root(runs_dir: str | None = None) -> Path:
    """``runs_root(runs_dir)``, checked to be a writable folder with space (``PathError`` naming
    ``--runs-dir`` or ``$FWK_RUNS_DIR`` otherwise)."""
    what = "--runs-dir" if runs_dir else ("$FWK_RUNS_DIR" if os.environ.get("FWK_RUNS_DIR") else "the runs folder")
    return check_dir(runs_root(runs_dir), what)


def check_cache_dir() -> None:
    """``$FWK_CACHE``, where set, checked to be a writable folder with space (``PathError``)."""
    if os.environ.get("FWK_CACHE"):
        check_dir(os.environ["FWK_CACHE"], "$FWK_CACHE")


def new_run_dir(root: Path, name: str) -> Path:
    """A new directory ``root/<name>-<UTC yyyymmdd-HHMMSS>`` (suffixed -2, -3... if taken), never an
    existing one, even when several processes start at once."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PathError(f"runs folder {root}: cannot create it ({exc.strerror})") from None
    base = root / f"{name}-{stamp}"
    p, i = base, 1
    while True:
        try:
            p.mkdir(parents=False, exist_ok=False)
            return p
        except FileExistsError:
            i += 1
            p = Path(f"{base}-{i}")
        except OSError as exc:
            raise PathError(f"runs folder {root}: cannot create {p.name} ({exc.strerror})") from None


# ----------------------------------------------------------------------------- run state

RUNNING, FAILED = "RUNNING", "FAILED"


class RunLock:
    """``RUNNING`` in a run directory, held with ``flock`` for as long as this process writes
    the run (the kernel drops the lock when the process dies, however it dies)."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / RUNNING
        self.fd: int | None = None

    def acquire(self) -> bool:
        """Take the lock; True when a ``RUNNING`` of a killed process was found (taken over).
        Raises FwkError while another live process holds it."""
        while True:
            existed = self.path.exists()
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, file_mode())
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                who = os.read(fd, 4096).decode(errors="replace").splitlines()[:1]
                os.close(fd)
                raise FwkError(f"{self.run_dir}: another fwk process is writing this run "
                               f"({who[0] if who else 'see RUNNING'}); wait for it to end") from None
            except OSError:  # a file system without locks (some network mounts): RUNNING still tells
                pass
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # the holder finished and removed it between our open and lock: again
                os.close(fd)
                continue
            started = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
            os.ftruncate(fd, 0)
            os.write(fd, (f"pid {os.getpid()} on {socket.gethostname()}, started {started}\n"
                          f"If that process is gone the run was killed: fwk run --resume {self.run_dir}\n").encode())
            self.fd = fd
            return existed

    def release(self, remove: bool = True) -> None:
        """Drop the lock, removing ``RUNNING`` first when ``remove``."""
        if self.fd is None:
            return
        if remove:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
        os.close(self.fd)
        self.fd = None


def run_state(run_dir) -> tuple[str, str]:
    """(state, detail) of a run directory: ``complete``, ``running`` (a live process holds its
    lock), ``killed`` (``RUNNING`` left by a process that is gone) or ``failed`` (``FAILED``:
    detail is the error's line)."""
    run_dir = Path(run_dir)
    failed = run_dir / FAILED
    if failed.exists():
        try:
            return "failed", failed.read_text(errors="replace").splitlines()[0]
        except (OSError, IndexError):
            return "failed", "see FAILED"
    running = run_dir / RUNNING
    if running.exists():
        try:
            fd = os.open(running, os.O_RDONLY)
        except FileNotFoundError:  # it finished just now
            return "complete", ""
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            who = os.read(fd, 4096).decode(errors="replace").splitlines()[:1]
            return "running", who[0] if who else ""
        except OSError:  # no locks on this file system: live or killed cannot be told apart
            return "killed", "or still running: this file system has no locks to tell"
        finally:
            os.close(fd)
        return "killed", "the process that wrote it is gone"
    return "complete", ""


def require_complete(run_dir, what: str = "") -> None:
    """Raise FwkError unless ``run_dir`` is a complete run (see ``run_state``)."""
    state, detail = run_state(run_dir)
    if state == "complete":
        return
    lead = f"{what} {run_dir}" if what else str(run_dir)
    if state == "running":
        raise FwkError(f"{lead}: still running ({detail}); wait for it to finish")
    raise FwkError(f"{lead}: the run {'failed' if state == 'failed' else 'was killed'} ({detail}); "
                   f"continue it with fwk run --resume {run_dir}")


def _worth_keeping(run_dir: Path) -> bool:
    """Whether a run directory holds work a resume would reuse: a trained model or a checkpoint,
    its own or a sub-run's (``reconstruct/models/`` of edit, a grid's configurations)."""
    keep = {"models", "checkpoints"}
    return any(p.is_file() and keep & set(p.relative_to(run_dir).parts[:-1]) for p in run_dir.rglob("*"))


def _append(exc: FwkError, text: str) -> None:
    """Add ``text`` to the one line ``exc`` prints (an OSError's through its strerror)."""
    if isinstance(exc, OSError) and exc.strerror:
        exc.strerror = f"{exc.strerror}{text}"
    else:
        exc.args = (f"{exc}{text}",)


def _write_failed(run_dir: Path, exc: BaseException) -> None:
    """``FAILED``: the error in one line, the traceback, the command that resumes (best effort:
    on a full disk there may be no room even for this)."""
    if isinstance(exc, KeyboardInterrupt) or (isinstance(exc, SystemExit)
                                              and isinstance(exc.__context__, KeyboardInterrupt)):
        line = "interrupted (Ctrl-C)"  # Lightning turns a Ctrl-C while training into sys.exit(1)
    elif isinstance(exc, Terminated):
        line = "terminated (SIGTERM)"
    elif isinstance(exc, FwkError):
        line = str(exc)
    else:
        line = f"{type(exc).__name__}: {exc}".splitlines()[0]
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    text = f"{line}\n\nContinue with: fwk run --resume {run_dir}\n\n{tb}"
    try:
        atomic_write_bytes(run_dir / FAILED, text.encode())
    except OSError:
        try:
            with open(run_dir / FAILED, "w") as f:
                f.write(line + "\n")
        except OSError:
            pass


def versions(registry: Registry) -> dict:
    """Python, platform, library and plugin versions and the git commit, for ``versions.json``."""
    from importlib import metadata

    out = {"python": sys.version.split()[0], "platform": platform.platform(), "fwk": __version__}
    for mod in ("numpy", "scipy", "torch", "lightning", "torch_geometric", "trimesh", "pyvista", "open3d"):
        try:  # the installed distribution's version: importing pyvista and open3d only for it took 1-3 s a run
            out[mod] = metadata.version(mod)
        except metadata.PackageNotFoundError:
            try:  # a module without distribution metadata (a source checkout on sys.path)
                out[mod] = getattr(__import__(mod), "__version__", "")
            except Exception:
                pass
    out["plugins"] = {}
    for e in registry:
        out["plugins"].setdefault(e.plugin, e.version)
    try:
        here = Path(__file__).resolve().parent
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        if commit.returncode == 0:
            out["git_commit"] = commit.stdout.strip()
            # tracked files changed since that commit: the run is not exactly the commit
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                   capture_output=True, text=True, timeout=5)
            if dirty.returncode == 0:
                out["git_dirty"] = bool(dirty.stdout.strip())
    except Exception:
        pass
    return out


CODE_KEYS = ("fwk", "git_commit", "git_dirty", "torch")

#: the key of ``versions.json`` that holds the SHA-256 of ``recipe.yaml`` as the run started
RECIPE_HASH = "recipe_sha256"


def recipe_hash(run_dir) -> str:
    """The SHA-256 of the run's ``recipe.yaml`` bytes."""
    return hashlib.sha256((Path(run_dir) / "recipe.yaml").read_bytes()).hexdigest()


def check_recipe_hash(run_dir, what: str = "") -> None:
    """Refuse a run whose ``recipe.yaml`` was edited after the run started: its SHA-256 differs
    from the one ``execute`` recorded in ``versions.json`` (its models and files come from the
    recipe as it was). A run without a recorded hash (an earlier version's) is not checked."""
    run_dir = Path(run_dir)
    try:
        recorded = json.loads((run_dir / "versions.json").read_text()).get(RECIPE_HASH)
    except (OSError, ValueError, AttributeError):
        return
    if isinstance(recorded, str) and recorded != recipe_hash(run_dir):
        raise FwkError(f"{what}{run_dir / 'recipe.yaml'}: edited after the run started (its SHA-256 differs "
                       f"from the one versions.json recorded); its results come from the recipe as it was: "
                       f"start a new run with the edited recipe")


def _started_side_by_side(run_dir: Path, mark: str = SIDE_BY_SIDE) -> bool:
    """Whether the run's versions.json carries ``mark`` (``SIDE_BY_SIDE``: written as a run starts
    since models are fitted side by side; ``SEEDS_SIDE_BY_SIDE``: since seeds run side by side);
    an unreadable one counts as a new run's."""
    try:
        stored = json.loads((Path(run_dir) / "versions.json").read_text())
    except (OSError, ValueError):
        return True
    return not isinstance(stored, dict) or mark in stored


def fix_threads(ctx: RunContext, created: bool) -> tuple[int, str]:
    """Fix the run's thread count as it starts (``fwk.engine.threads.pin``): every training of the
    run uses it, whatever starts or ends beside it, so its numbers do not depend on the machine's
    load. A new run takes ``thread_budget()`` (``--threads``/``FWK_THREADS``, an executor's
    allocation, ``OMP_NUM_THREADS``, else the cores shared with the fwk processes and other work
    running now) and records it in ``versions.json``; ``--resume`` takes the count recorded there
    unless one is given (then it says that the run's numbers now come from two counts). Inside a
    run already pinned (a run started from a run's process) the outer count stays. Said once in
    the log: ``threads: N (why), fixed for this run``."""
    if pinned() is not None:
        return pinned()
    recorded = None if created else recorded_threads(ctx.run_dir)
    given = explicit_threads()
    if recorded is not None and given is None:
        n, why = recorded[0], f"as the run started: {recorded[1]}"
    else:
        n, why = thread_budget()
    pin(n, why)
    forget_reported(ctx.log_file)  # said at every start and resume
    report_threads(ctx.log, n, f"{why}; fixed for this run, fwk run --resume reuses it", ctx.log_file)
    if recorded is not None and n != recorded[0]:
        ctx.log(f"threads: this run started with {recorded[0]} and resumes with {n} ({why}): its numbers "
                f"now come from two thread counts (fwk run --resume --threads {recorded[0]} keeps one)")
    if created or recorded is None:  # a resume keeps the start's record (record_resume adds its own count)
        try:
            stored = json.loads(ctx.path("versions.json").read_text())
        except (OSError, ValueError):
            stored = {}
        stored = stored if isinstance(stored, dict) else {}
        ctx.write_json("versions.json", {**stored, "threads": n, "threads_why": why})
    return n, why


def record_resume(ctx: RunContext, registry: Registry) -> None:
    """Append the code a resume runs with to the run's ``versions.json`` (``resumed``: one entry
    per resume, with its time) and log a line when it differs from the code that ran the run last
    (its start, or its latest resume): the run's numbers then come from more than one version of
    fwk. A ``versions.json`` that is missing or unreadable is started afresh."""
    path = ctx.path("versions.json")
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        stored = {}
    now = versions(registry)
    entry = {"at": _dt.datetime.now().isoformat(timespec="seconds"),
             **{k: now[k] for k in CODE_KEYS if k in now}}
    if pinned() is not None:
        entry["threads"] = pinned()[0]
    before = (stored.get("resumed") or [stored])[-1]
    changed = [k for k in CODE_KEYS if k in entry and k in before and entry[k] != before[k]]
    if changed:
        ctx.log("resuming with other code than the run last ran with: "
                + ", ".join(f"{k} {before[k]} -> {entry[k]}" for k in changed)
                + " (versions.json lists every resume)")
    stored.setdefault("resumed", []).append(entry)
    ctx.write_json("versions.json", stored)


def run_task(resolved, ctx: RunContext) -> None:
    """Build the recipe's task and run it in ``ctx``; a recipe with ``seeds`` runs it once per
    seed, in sub-runs of ``ctx`` on one split (``fwk.seeds.run_seeds``), unless the task fans
    seeds out itself (its class says ``fans_out_seeds = True``: the grid)."""
    if resolved.seeds is not None and not fans_out_seeds(resolved.task.cls):
        run_seeds(resolved, ctx)
        return
    task = resolved.task.build()
    task.run(ctx)


def _terminated(signum, frame):
    raise Terminated("terminated (SIGTERM)")


def execute(recipe_path: str, overrides: list[str] | None = None, runs_dir: str | None = None,
            resume: str | None = None, quiet: bool = False, registry: Registry | None = None,
            cache: Cache | None = None, device: str | None = None) -> Path:
    """``fwk run``: validate the recipe and the output folders first, then create the run
    directory and run (see the module docstring for what a run directory holds when it fails).
    The process registers among those that share the cores (``fwk.engine.threads``)."""
    if device == "cuda":
        _check_cuda()
    registry = registry or get_registry()
    register()
    outer_pin = pinned()  # a run inside a run (from Python) keeps the outer run's thread count
    if resume:
        run_dir = Path(resume)
        if not run_dir.is_dir():
            raise FwkError(f"--resume {resume}: not a folder")
        if not (run_dir / "recipe.yaml").exists():
            raise FwkError(f"--resume {resume}: not a run directory (no recipe.yaml)")
        check_recipe_hash(run_dir, "--resume: ")
        refuse_pickled(run_dir)  # an earlier version's pickles: `fwk convert`, before anything is written
        try:  # every check of a recipe file: a key given twice, an alias bomb, not UTF-8 (one line)
            data = read_recipe_file(run_dir / "recipe.yaml", "run recipe")
        except RecipeError as exc:
            raise FwkError(f"--resume: {exc}") from None
        if recipe_path:
            fresh = load_recipe(recipe_path, overrides)
            fresh["source"] = fresh.pop("_source", None)
            if to_plain(fresh) != {k: v for k, v in data.items()}:
                raise FwkError(f"--resume {resume}: the recipe differs from the one the run was started with")
        resolved = resolve(data, registry)
        check_dir(run_dir, "--resume")
        if cache is None:
            check_cache_dir()
        created = False
    else:
        data = load_recipe(recipe_path, overrides)
        resolved = resolve(data, registry)
        root = check_runs_root(runs_dir)
        if cache is None:
            check_cache_dir()
        run_dir = new_run_dir(root, resolved.name)
        created = True
    lock = RunLock(run_dir)
    try:
        killed = lock.acquire()
    except BaseException:
        if created:
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    # SIGTERM (a scheduler's time limit, `kill`) becomes an exception here, so the run is marked
    # FAILED like any other stop; Lightning's own handler calls this one too while it trains
    previous = signal.signal(signal.SIGTERM, _terminated) \
        if threading.current_thread() is threading.main_thread() else None
    try:
        ctx = RunContext(run_dir, registry, cache, resolved.seed, recipe=resolved.data, train=resolved.train,
                         device=device, quiet=quiet, resume=bool(resume))
        ctx.source = resolved.source
        if created:
            plain = {k: v for k, v in resolved.data.items() if k != "_source"}
            if resolved.source:
                plain["source"] = resolved.source  # the recipe file: relative paths resolve from it
            ctx.write_text("recipe.yaml", yaml.safe_dump(plain, sort_keys=False))
            ctx.write_json("versions.json", {**versions(registry), RECIPE_HASH: recipe_hash(run_dir),
                                             SIDE_BY_SIDE: True, SEEDS_SIDE_BY_SIDE: True})
        ctx.log(f"fwk run {resolved.name}: task {resolved.task.name}, run directory {run_dir}")
        fix_threads(ctx, created)
        if resume and not _started_side_by_side(run_dir):
            ONE_AFTER_ANOTHER[0] = True
            ctx.log("this run started before fwk fitted models side by side (2026-12-03): its models are fitted "
                    "one after another, as when it started")
        if resume and not _started_side_by_side(run_dir, SEEDS_SIDE_BY_SIDE) and resolved.seeds \
                and not fans_out_seeds(resolved.task.cls):
            SEEDS_ONE_AFTER_ANOTHER[0] = True
            ctx.log("this run started before fwk ran seeds side by side (2026-12-03): its seeds run one after "
                    "another, as when it started")
        if resume:
            for tmp in run_dir.rglob(".*.tmp"):  # writes a killed process cut short (this one holds the lock)
                tmp.unlink()
            failed = run_dir / FAILED
            if failed.exists():
                why = (failed.read_text(errors="replace").splitlines() or ["?"])[0]
                ctx.log(f"resuming a run that failed ({why})")
                failed.unlink()
            elif killed:
                ctx.log("resuming a run whose process was killed")
            record_resume(ctx, registry)
        run_task(resolved, ctx)
        ctx.log(f"done: {run_dir}")
    except BaseException as exc:
        if isinstance(exc, FwkError) and created and not _worth_keeping(run_dir):
            lock.release()
            shutil.rmtree(run_dir, ignore_errors=True)
            # the log printed the directory's name: say it is gone, and why nothing is kept
            _append(exc, f"; nothing was trained yet, so no run directory is left ({run_dir.name} removed)")
            raise
        _write_failed(run_dir, exc)
        lock.release()
        if isinstance(exc, FwkError):  # still one line: what to fix, then where the work so far is
            _append(exc, f"; the run so far is kept: fwk run --resume {run_dir}")
        elif not quiet:
            print(f"fwk: the run failed; {run_dir / FAILED} holds the error; "
                  f"continue with: fwk run --resume {run_dir}", file=sys.stderr)
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if outer_pin is None:
            unpin()  # this run's count ends with it (a run inside a run keeps the outer one's)
            ONE_AFTER_ANOTHER[0] = False
            SEEDS_ONE_AFTER_ANOTHER[0] = False
    lock.release()
    return run_dir
