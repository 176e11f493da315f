"""Where a grid's members run: ``local`` (in this process, or side by side in processes forked
from it) or ``ray`` (Ray tasks, on a local Ray instance or an existing cluster).

``local`` runs the members side by side on the CPU when the grid's ``train.side_by_side`` (default
true) allows it and the run has T >= 2 threads: w = min(T, jobs) at a time (a job: a member, or one
seed of a member), each with T // w threads, jobs counted over the whole grid (finished ones
included) so that a member's count does not depend on what a resume has left (``fwk.sidebyside``).

Both executors run a member the same way (``run_member``): its recipe resolved afresh, a run
context on its sub-run folder ``<grid run>/<member>/`` with ``resume`` set (a member killed
midway continues from its checkpoints), the task run, and the outcome returned as a small
mapping (``{"ok": True}`` or ``{"ok": False, "error": ..., "traceback": ...}``) instead of an
exception, so one failing member never stops the others. A member that fails gets a ``FAILED``
file in its sub-run holding the error (removed when it is run again and succeeds).

On Ray each member is one task declaring ``executor.cpus`` CPUs and ``executor.gpus`` GPUs;
its process computes with as many threads as CPUs it was given (``FWK_ALLOCATED_CPUS``, see
``fwk.engine.threads``), so members that run side by side never oversubscribe the cores. The
sub-runs are written by the workers: on a cluster of several machines the runs folder (and
``FWK_CACHE``) must be on a file system every node mounts at the same path.
"""
from __future__ import annotations

import logging
import os
import time
import traceback
from dataclasses import dataclass, fields
from pathlib import Path

from fwk.cache import Cache, atomic_write_bytes
from fwk.engine.distributed import die_with_parent
from fwk.engine.threads import ENV_ALLOCATED, available_cores, unregister
from fwk.errors import FwkError, RecipeError
from fwk.plugins import get_registry
from fwk.recipes import resolve
from fwk.registry import did_you_mean
from fwk.runs import FAILED, RunContext, run_task  # FAILED: the run-state file fwk.runs.run_state reads

EXECUTORS = ("local", "ray")


@dataclass
class Executor:
    """The recipe's ``executor:`` of a grid: a name (``executor: ray``) or a mapping.

    * ``name``: ``local`` (default; members one after another in this process) or ``ray``;
    * ``address``: Ray only; an existing cluster (``ray://head:10001``, or ``auto`` for the one
      this machine belongs to); unset: a local Ray instance started for the grid and stopped
      after it;
    * ``cpus``, ``gpus``: what each member declares to Ray (fractions allowed); a member
      computes with ``max(1, int(cpus))`` threads;
    * ``num_cpus``, ``num_gpus``: the size of a local instance (default: the cores this process
      may use, and Ray's own GPU detection).
    """

    name: str = "local"
    address: str | None = None
    cpus: float = 1.0
    gpus: float = 0.0
    num_cpus: int | None = None
    num_gpus: int | None = None

    def __post_init__(self):
        if self.name not in EXECUTORS:
            raise RecipeError(f"executor: expected one of {', '.join(EXECUTORS)}, got {self.name!r}"
                              f"{did_you_mean(str(self.name), EXECUTORS)}")
        for key in ("cpus", "gpus"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
                raise RecipeError(f"executor.{key}: expected a number >= 0, got {v!r}")
        if self.cpus == 0 and self.gpus == 0:
            raise RecipeError("executor.cpus: a member needs some CPUs or GPUs (both are 0)")
        for key in ("num_cpus", "num_gpus"):
            v = getattr(self, key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
                raise RecipeError(f"executor.{key}: expected an integer >= 0, got {v!r}")
        if self.address is not None and not isinstance(self.address, str):
            raise RecipeError(f"executor.address: expected a Ray address (ray://host:port or auto), got {self.address!r}")
        if self.name == "local" and (self.address or self.num_cpus or self.num_gpus):
            raise RecipeError("executor: address, num_cpus and num_gpus are Ray settings; "
                              "set executor.name: ray (or executor=ray)")

    @classmethod
    def from_recipe(cls, value) -> "Executor":
        """The executor of a recipe value: a name, a mapping of the fields above, or None."""
        if value is None:
            return cls()
        if isinstance(value, Executor):
            return value
        if isinstance(value, str):
            return cls(name=value)
        if not isinstance(value, dict):
            raise RecipeError(f"executor: expected local, ray or a mapping with name, got {value!r}")
        names = [f.name for f in fields(cls)]
        bad = [k for k in value if k not in names]
        if bad:
            raise RecipeError(f"executor.{bad[0]}: unknown setting{did_you_mean(str(bad[0]), names)}")
        return cls(**value)

    @property
    def threads(self) -> int:
        """The threads a member computes with on Ray: its whole CPUs, at least one."""
        return max(1, int(self.cpus))


# ------------------------------------------------------------------------- one member

def member_job(name: str, sub: Path, resolved, ctx) -> dict:
    """What ``run_member`` needs, as plain data (it crosses to Ray workers)."""
    recipe = {k: v for k, v in resolved.data.items() if k != "_source"}
    return {"name": name, "run_dir": str(Path(sub).resolve()), "recipe": recipe, "source": resolved.source,
            "cache": str(Path(ctx.cache.root).resolve()), "cache_enabled": bool(ctx.cache.enabled),
            "device": ctx.device, "quiet": ctx.quiet, "log_file": str(Path(ctx.log_file).resolve()),
            "threads": None}  # an executor's allocation, set by run_ray


def run_member(job: dict, registry=None) -> dict:
    """Run one grid member in its sub-run folder (resuming whatever it left): ``{"ok": True,
    "seconds": s}`` or ``{"ok": False, "error": one line, "traceback": text or None}``. A
    ``FAILED`` file in the sub-run holds a failure's error and traceback."""
    sub = Path(job["run_dir"])
    t0 = time.perf_counter()
    if job.get("on_ray"):
        # killed with the Ray worker's parent, the raylet: on a local instance the raylet dies with the
        # driver (fwk run), however it dies, and without this the worker trained on into the run directory
        # (measured: epoch 48 at a kill -9 of the grid, epoch 113 three seconds later), racing with the
        # `fwk run --resume` that trains the same member. On a cluster the node's raylet lives on.
        die_with_parent()
    if job.get("threads"):
        os.environ[ENV_ALLOCATED] = str(job["threads"])
    try:
        registry = registry or get_registry()
        resolved = resolve({**job["recipe"], "_source": job["source"]}, registry)
        ctx = RunContext(sub, registry, Cache(job["cache"], enabled=job["cache_enabled"]), resolved.seed,
                         recipe=resolved.data, train=resolved.train, device=job["device"], quiet=job["quiet"],
                         resume=True, log_file=Path(job["log_file"]))
        ctx.source = resolved.source
        run_task(resolved, ctx)
    except Exception as exc:  # a member's failure is reported, the others go on
        user = isinstance(exc, FwkError)
        error = str(exc) if user else f"{type(exc).__name__}: {exc}"
        tb = None if user else traceback.format_exc()
        try:
            atomic_write_bytes(sub / FAILED, (error + "\n" + (tb or "")).encode())
        except OSError:
            pass
        return {"ok": False, "error": error.splitlines()[0] if error else type(exc).__name__, "traceback": tb,
                "seconds": time.perf_counter() - t0}
    finally:
        if job.get("threads"):
            os.environ.pop(ENV_ALLOCATED, None)
            unregister()  # a Ray worker outlives its task: it no longer computes for fwk
    (sub / FAILED).unlink(missing_ok=True)
    return {"ok": True, "seconds": time.perf_counter() - t0}


# ------------------------------------------------------------------------- executors

def run_local(jobs: list[dict], log, registry=None, side_by_side=None) -> dict[str, dict]:
    """Run the members one after another in this process (with ``registry``, default the
    process-wide one): {name: outcome}. ``side_by_side``: (workers, threads, T, log file) of
    ``fwk.forked.plan``: the members run ``workers`` at a time instead, each in a process
    forked from this one with ``threads`` of the run's T threads (``run_forked``)."""
    if side_by_side is not None:
        return _run_forked(jobs, log, registry, *side_by_side)
    out = {}
    for i, job in enumerate(jobs):
        log(f"[{i + 1}/{len(jobs)}] {job['name']}")
        out[job["name"]] = outcome = run_member(job, registry)
        if not outcome["ok"]:
            log(f"grid member {job['name']} failed: {outcome['error']}")
    return out


def _run_forked(jobs: list[dict], log, registry, workers: int, threads: int, T: int, log_file) -> dict[str, dict]:
    """``run_local``'s members side by side: ``run_member`` in forked children (``fwk.sidebyside``),
    ``workers`` at a time with ``threads`` threads each, logged as they finish; a child that ends
    without an outcome (killed) is a failed member."""
    from fwk.forked import run_forked

    why = (f"{workers} grid members side by side on the run's {T} threads, {threads} each; "
           "train.side_by_side: false runs them one after another")
    log(f"{len(jobs)} member run{'s' if len(jobs) != 1 else ''} side by side, {workers} at a time with {threads} "
        f"thread{'s' if threads > 1 else ''} each (the run's {T}; fixed by the run's count and the grid's members; "
        f"train.side_by_side: false runs them one after another with {T})")
    count = [0]

    def done(name, o):
        count[0] += 1
        outcome = o.get("result") if o.get("ok") else {
            "ok": False, "error": o.get("message", "").splitlines()[0] if o.get("message") else o.get("kind", "?"),
            "traceback": o.get("traceback"), "seconds": 0.0}
        out[name] = outcome
        if outcome["ok"]:
            log(f"[{count[0]}/{len(jobs)}] {name}: finished in {outcome['seconds']:.1f} s")
        else:
            log(f"[{count[0]}/{len(jobs)}] grid member {name} failed: {outcome['error']}")

    out: dict[str, dict] = {}
    byname = {job["name"]: job for job in jobs}
    run_forked({name: (lambda job=job: run_member(job, registry)) for name, job in byname.items()}, workers,
               threads, why, log_file, stop_on_error=False, on_done=done,
               prefixes={name: f"[{name}] " for name in byname})  # which member said each line
    return {job["name"]: out[job["name"]] for job in jobs}


def _ray():
    # deferred: Ray costs ~0.9 s of import time (measured: python -c "import ray"), which
    # `fwk list` (it imports every plugin) and local grids need not pay; and it is an extra
    try:
        import ray
    except ImportError:
        raise FwkError("executor: ray needs Ray: pip install 'fwk[ray]' (or pip install ray)") from None
    return ray


def ray_init_kwargs(executor: Executor, quiet: bool) -> dict:
    """``ray.init``'s arguments for a grid: the cluster at ``executor.address``, or a local instance
    with ``executor.num_cpus`` (default: the available cores) and ``num_gpus``, a small object store
    and the members at the driver's own priority.

    Ray starts its workers 15 nice levels below the process that started it (``worker_niceness``,
    default 15), which is right for helper work beside a driver that computes, but a grid's members
    *are* the computation: beside other work they were starved (measured 2026-12-05, a 187-vertex
    member resumed beside two trainings: about 1.8 s an epoch at nice 15 against about 0.2 s for the
    same member in a local grid), while fwk's local executor and side-by-side processes run at the
    driver's priority. ``worker_niceness: 0`` keeps the workers at the raylet's, i.e. the driver's,
    niceness (``nice -n 10 fwk run`` still lowers the whole grid). A cluster's own settings are left
    to it."""
    kw = {"include_dashboard": False, "log_to_driver": not quiet, "logging_level": logging.ERROR}
    if executor.address:
        kw["address"] = executor.address
        return kw
    kw["num_cpus"] = executor.num_cpus or available_cores()
    # members return a few numbers and write their sub-runs themselves: a small object
    # store, not Ray's default of 30 % of the memory in shared memory
    kw["object_store_memory"] = 128 * 2**20
    if executor.num_gpus is not None:
        kw["num_gpus"] = executor.num_gpus
    kw["_system_config"] = {"worker_niceness": 0}
    return kw


def run_ray(jobs: list[dict], executor: Executor, log) -> dict[str, dict]:
    """Run the members as Ray tasks (each declaring ``executor.cpus`` / ``gpus``) on a local Ray
    instance (``ray_init_kwargs``), or the cluster at ``executor.address``: {name: outcome}, logged
    as they finish."""
    ray = _ray()
    started = False
    if not ray.is_initialized():
        kw = ray_init_kwargs(executor, all(j["quiet"] for j in jobs))
        try:
            ray.init(**kw)
        except ConnectionError as exc:
            raise FwkError(f"executor.address {executor.address}: no Ray cluster there ({exc})") from None
        started = True
    try:
        total = ray.cluster_resources()
        if total.get("CPU", 0) < executor.cpus or total.get("GPU", 0) < executor.gpus:
            raise FwkError(f"executor: each member asks for {executor.cpus:g} CPUs and {executor.gpus:g} GPUs; "
                           f"the Ray cluster has {total.get('CPU', 0):g} CPUs and {total.get('GPU', 0):g} GPUs")
        remote = ray.remote(run_member).options(num_cpus=executor.cpus, num_gpus=executor.gpus, max_retries=0,
                                                name="fwk-grid-member")
        log(f"ray: {len(jobs)} member{'s' if len(jobs) != 1 else ''} on {total.get('CPU', 0):g} CPUs"
            f" and {total.get('GPU', 0):g} GPUs, {executor.cpus:g} CPUs and {executor.gpus:g} GPUs each")
        pending = {remote.remote({**job, "threads": executor.threads, "on_ray": True}): job["name"] for job in jobs}
        out, done = {}, 0
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(ready[0])
            done += 1
            try:
                outcome = ray.get(ready[0])
            except Exception as exc:  # the worker died (killed, out of memory) or Ray failed it
                outcome = {"ok": False, "error": f"the Ray task failed: {type(exc).__name__}: "
                           f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}",
                           "traceback": str(exc)}
            out[name] = outcome
            if outcome["ok"]:
                log(f"[{done}/{len(jobs)}] {name}: finished in {outcome['seconds']:.1f} s")
            else:
                log(f"[{done}/{len(jobs)}] grid member {name} failed: {outcome['error']}")
        return out
    finally:
        if started:
            ray.shutdown()
