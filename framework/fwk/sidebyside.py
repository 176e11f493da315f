"""The models of a run fitted side by side, one forked process each, when one model's fitting
cannot use the run's threads (issue 28).

A second thread speeds one training up by less than a second process would: two 1-thread
trainings together make 1.09x (the thesis-width vcconv VAE) to 1.52x (the main job's PB
network) the steps per second of one 2-thread training (``benchmarks/side_by_side.py``,
``docs/methods/autoencoders.md``), and Deformation Transfer's sparse factorisations use one
thread. A run with T threads that fits its m models one after another leaves that unused.
``fit_models`` fits them w = min(T, m) at a time instead, each
in a child process forked after the data are prepared (the child shares them copy-on-write: no
second load), with ``T // w`` threads; the child fits its model exactly as ``fit_or_resume``
does (its checkpoints, curves and TensorBoard logs under its label, then
``models/<label>.safetensors``) and exits; the run's process, which computes nothing meanwhile,
loads each saved state in the recipe's order. ``train.side_by_side: false`` fits them one
after another, each with the run's T threads.

**Numbers.** A model's numbers depend on the thread count it trains with (the order of
floating-point sums), so that count must not depend on what is left to fit: it is
``T // min(T, m)`` with m the models of the recipe, also when a resume has fewer left to fit.
A run's numbers therefore depend on T and the recipe only, as before; a model fitted side by
side with one thread is bit for bit the model a 1-thread run fits
(``tests/core/test_side_by_side.py``). Each training records its own count (``curves/``), and the
log says the plan once.

``run_forked`` is the machinery (jobs in forked children, w at a time, outcomes back as JSON);
a grid's local executor runs its members with it the same way (``fwk_grid.executors``).

**When.** On Linux (``os.fork``: Windows has none, and macOS's system frameworks are not safe
to fork), on the CPU only (a forked child cannot use a CUDA context its parent created), not with
``train.strategy: ddp`` (whose ranks already share the cores), with T >= 2 and at least two
models in the recipe. Everything else of the task (data, predictions, metrics, figures) runs in
the run's process with T threads.

**Failures.** A child that raises sends its exception back (an fwk error keeps its class and one
line; any other its traceback); the run's process starts no other model, lets the running ones
finish (as one after another, the models fitted before a failure are kept) and raises it;
``fwk run --resume`` fits what is left. A child killed (out of memory) is reported with its
signal. A child dies with the run's process
(``PR_SET_PDEATHSIG``), and Ctrl-C stops them all.
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


def plan(ctx, n_models: int) -> tuple[int, int, int] | None:
    """(workers w, threads per model, the run's threads T) for fitting ``n_models`` models side by
    side in the run of ``ctx``, or None where they are fitted one after another (see the module
    docstring: ``train.side_by_side``, the device, DDP, T < 2, fewer than 2 models, a resumed run
    that started before side by side: ``fwk.runs.ONE_AFTER_ANOTHER``)."""
    from .engine.threads import thread_budget
    from .runs import ONE_AFTER_ANOTHER

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
            from . import runs

            runs.LOG_PREFIX[0] = prefix
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


def _reraise(label: str, out: dict, what: str | None = None, doing: str = "fitting ",
             one_at_a_time: str = "fits one model at a time") -> None:
    """Raise in the run's process what a child's outcome ``out`` says: an fwk error with its class,
    Ctrl-C as KeyboardInterrupt, a bug with the child's traceback, a killed child with its signal.
    ``what``: whom the message names (``models.<label>``); ``doing``: what its process did."""
    what = what or f"models.{label}"
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


def fit_side_by_side(jobs: dict, ctx, workers: int, threads: int, T: int) -> dict[str, float]:
    """Run ``jobs`` (label -> a function that fits and saves that model) in forked children,
    ``workers`` at a time with ``threads`` threads each (``T``: the run's), logging through
    ``ctx``; returns label -> seconds of each child's fitting; the first failure is raised
    once the running children end. See the module docstring."""
    why = (f"{workers} models fitted side by side on the run's {T} threads, {threads} each; "
           "train.side_by_side: false fits them one after another")
    ctx.log(f"fitting {len(jobs)} model{'s' if len(jobs) > 1 else ''} side by side, {workers} at a time with "
            f"{threads} thread{'s' if threads > 1 else ''} each (the run's {T}; a model's thread count is fixed by "
            f"the run's and the recipe's models: train.side_by_side: false fits them one after another with {T})")
    first: list = []

    def done(label, out):
        if not out.get("ok") and not first:
            first.append((label, out))
            ctx.log(f"[{label}] failed; no other model starts, those still fitting finish (their work is kept "
                    "for fwk run --resume), then the run stops")

    outcomes = run_forked(jobs, workers, threads, why, ctx.log_file, stop_on_error=True, on_done=done)
    if first:
        label, out = first[0]
        _reraise(label, out)
    return {label: float(out["seconds"]) for label, out in outcomes.items()}
