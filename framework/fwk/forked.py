"""Jobs in forked processes, a few at a time with a fixed thread count each (issue 28): the
machinery of a run's models side by side (``fwk.sidebyside``), its seeds side by side
(``fwk.seeds``) and a grid's members (``fwk_grid``'s local executor).

``plan`` says whether a run may fork and with how many workers; ``run_forked`` forks the jobs
(each child pins its threads, prefixes its printed and logged lines, dies with the run's process,
and sends its outcome back as JSON); ``run_or_raise`` logs and raises the first failure once the
running jobs end; ``reraise`` turns a child's outcome back into the exception it raised. The
rules (when, numbers, failures) are ``fwk.sidebyside``'s docstring.
"""
from __future__ import annotations

import io
import json
import os
import signal
import sys
import time
import traceback

from . import errors as _errors
from .engine.distributed import die_with_parent
from .errors import FwkError

#: how often the run's process looks at its children (seconds)
POLL = 0.05
#: what this process puts before each line it writes to a log file (set in a forked child)
LOG_PREFIX = [""]
#: True while this process resumes a run started before models were fitted side by side
#: (2026-12-03): ``plan`` then fits its models one after another, as they were when it started
ONE_AFTER_ANOTHER = [False]
#: True while this process resumes a run started before seeds ran side by side: its seeds run in turn
SEEDS_ONE_AFTER_ANOTHER = [False]


def plan(ctx, n_models: int) -> tuple[int, int, int] | None:
    """(workers w, threads per model, the run's threads T) for fitting ``n_models`` models side by
    side in the run of ``ctx``, or None where they are fitted one after another (see the module
    docstring: ``train.side_by_side``, the device, DDP, T < 2, fewer than 2 models, a resumed run
    that started before side by side: ``ONE_AFTER_ANOTHER``)."""
    from .engine.threads import thread_budget

    train = getattr(ctx, "train", None)
    if ONE_AFTER_ANOTHER[0]:  # resuming a run started before side by side: as it started
        return None
    if not sys.platform.startswith("linux"):  # fork: none on Windows, unsafe with macOS's frameworks
        return None
    if n_models < 2 or train is None or not getattr(train, "side_by_side", True):
        return None
    if getattr(ctx, "device", "cpu") != "cpu" or train.accelerator not in ("auto", "cpu") or train.strategy == "ddp":
        return None
    if "torch" in sys.modules and sys.modules["torch"].cuda.is_initialized():
        return None
    T = thread_budget()[0]
    if T < 2:
        return None
    w = min(T, n_models)
    return w, T // w, T


class _Prefixed(io.TextIOBase):
    """A text stream writing ``prefix`` at the start of every line it passes to ``stream``."""

    def __init__(self, stream, prefix: str):
        self.stream, self.prefix, self.at_start = stream, prefix, True

    def write(self, text: str) -> int:
        parts = []
        for piece in text.splitlines(keepends=True):
            if self.at_start:
                parts.append(self.prefix)
            parts.append(piece)
            self.at_start = piece.endswith(("\n", "\r"))
        self.stream.write("".join(parts))
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return self.stream.isatty()

    def fileno(self) -> int:
        return self.stream.fileno()


def _child(work, threads: int, why: str, wfd: int, log_file, prefix: str = "") -> None:
    """In the forked child: run ``work()`` with ``threads`` threads (``prefix`` before every line
    it prints and logs), write the outcome as JSON to ``wfd`` and end the process (never returns)."""
    code = 1
    out: dict = {}
    try:
        if prefix:
            LOG_PREFIX[0] = prefix
            sys.stdout = _Prefixed(sys.stdout, prefix)
        die_with_parent()  # Ctrl-C reaches the children as it reaches the run (the same disposition)
        from .engine import threads as th

        th._registered.clear()  # the parent's registration is the parent's to remove
        os.environ[th.ENV_THREADS] = str(threads)  # wins over the pin, an allocation, OMP_NUM_THREADS
        th.pin(threads, why)
        th._threads_reported.setdefault(log_file, set()).add(threads)  # the run's process said the plan
        th.apply_threads()
        t0 = time.perf_counter()
        result = work()
        out.update(ok=True, seconds=time.perf_counter() - t0, result=result)
        code = 0
    except BaseException as exc:  # everything goes back to the run's process
        out.update(ok=False, kind=type(exc).__name__, fwk=isinstance(exc, FwkError), message=str(exc),
                   traceback=traceback.format_exc())
    finally:
        try:
            data = json.dumps(out).encode()
            while data:
                data = data[os.write(wfd, data):]
            os.close(wfd)
            sys.stdout.flush()
            sys.stderr.flush()
            from .engine import threads as th

            th.unregister()
        finally:
            os._exit(code)


def _read_all(fd: int, buf: bytearray) -> None:
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            return
        if not chunk:
            return
        buf.extend(chunk)


def run_forked(jobs: dict, workers: int, threads: int, why: str, log_file, stop_on_error: bool = True,
               on_done=None, prefixes: dict | None = None) -> dict[str, dict]:
    """Run ``jobs`` (name -> a function of no arguments returning JSON-able data or None) in
    forked children, ``workers`` at a time with ``threads`` threads each, in the order given.
    Returns name -> outcome: ``{"ok": True, "seconds": s, "result": ...}``, or ``{"ok": False,
    "kind", "fwk", "message", "traceback"}`` for one that raised, or ``{"ok": False, "killed":
    how, "message"}`` for one that ended without a word (a signal). ``stop_on_error``: after a
    failure start no other job (the running ones end); ``on_done(name, outcome)`` as each ends;
    ``prefixes``: name -> what the job's printed and logged lines start with. Ctrl-C (or any
    error here) stops the children."""
    import torch  # noqa: F401  (loaded before forking: every child then shares it)

    todo = list(jobs)
    running: dict[int, tuple[str, int, bytearray]] = {}
    outcomes: dict[str, dict] = {}
    sys.stdout.flush()
    sys.stderr.flush()

    def stop_all():
        for pid in running:
            try:
                os.kill(pid, signal.SIGTERM)
            except OSError:
                pass
        for pid in list(running):
            try:
                os.waitpid(pid, 0)
            except OSError:
                pass
            os.close(running.pop(pid)[1])

    failed = False
    try:
        while (todo and not failed) or running:
            while todo and not failed and len(running) < workers:
                name = todo.pop(0)
                r, w = os.pipe()
                pid = os.fork()
                if pid == 0:  # the child
                    os.close(r)
                    _child(jobs[name], threads, why, w, log_file, (prefixes or {}).get(name, ""))
                os.close(w)
                os.set_blocking(r, False)
                running[pid] = (name, r, bytearray())
            time.sleep(POLL)
            for pid in list(running):
                name, r, buf = running[pid]
                _read_all(r, buf)
                done, status = os.waitpid(pid, os.WNOHANG)
                if done == 0:
                    continue
                _read_all(r, buf)  # what the child wrote before it ended
                os.close(r)
                del running[pid]
                try:
                    out = json.loads(bytes(buf).decode())
                except ValueError:
                    sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
                    how = f"was killed by signal {sig} ({signal.Signals(sig).name})" if sig else \
                        f"ended with status {os.WEXITSTATUS(status)}"
                    out = {"ok": False, "killed": how, "message": f"its side-by-side process {how} without a result"}
                outcomes[name] = out
                failed = failed or (stop_on_error and not out.get("ok"))
                if on_done is not None:
                    on_done(name, out)
    except BaseException:
        stop_all()
        raise
    return outcomes


def reraise(label: str, out: dict, what: str = "models.{label}", doing: str = "fitting ",
            one_at_a_time: str = "fits one model at a time") -> None:
    """Raise in the run's process what a child's outcome ``out`` says: an fwk error with its class,
    Ctrl-C as KeyboardInterrupt, a bug with the child's traceback, a killed child with its signal.
    ``what``: whom the message names (formatted with ``label``); ``doing``: what its process did."""
    what = what.format(label=label)
    if out.get("killed"):
        why = (f"out of memory? train.side_by_side: false {one_at_a_time}" if "SIGKILL" in out["killed"]
               else "stopped from outside")
        raise FwkError(f"{what}: its side-by-side {doing}process {out['killed']} without a result ({why})")
    if out.get("fwk"):
        cls = getattr(_errors, out.get("kind", ""), None)
        cls = cls if isinstance(cls, type) and issubclass(cls, FwkError) else FwkError
        raise cls(out.get("message", ""))
    if out.get("kind") == "KeyboardInterrupt":
        raise KeyboardInterrupt
    raise RuntimeError(f"{what}: {doing}failed in its side-by-side process:\n{out.get('traceback', '')}")


def run_or_raise(jobs: dict, ctx, workers: int, threads: int, why: str, kind: str, prefixes: dict | None = None,
                 **reraise_kw) -> dict[str, dict]:
    """``run_forked`` with ``stop_on_error``: the first failure is logged through ``ctx`` (no other
    ``kind`` starts; those running finish, their work kept for ``fwk run --resume``) and raised
    (``reraise`` with ``reraise_kw``) once the running jobs end; else the outcomes."""
    first: list = []

    def done(name, out):
        if not out.get("ok") and not first:
            first.append((name, out))
            ctx.log(f"[{name}] failed; no other {kind} starts, those still running finish (their work is kept "
                    "for fwk run --resume), then the run stops")

    outcomes = run_forked(jobs, workers, threads, why, ctx.log_file, stop_on_error=True, on_done=done,
                          prefixes=prefixes)
    if first:
        name, out = first[0]
        reraise(name, out, **reraise_kw)
    return outcomes
