"""Several devices with DDP (``train.devices: N, train.strategy: ddp``), launched by fwk.

Lightning's own ``ddp`` starts ranks 1..N-1 by running the script's command line again, which
for ``fwk run`` would mean a second run directory, a second report and a second log. fwk's
launcher starts each extra rank as ``python -m fwk.rank JOB`` instead: the rank
reopens the run directory rank 0 is writing (its ``recipe.yaml``), reruns the task in resume
mode with its output silenced (data from the cache, finished models and trainings loaded,
nothing retrained), joins rank 0 in the one training that is running, and exits when it ends.
Only rank 0 writes: checkpoints (Lightning's rule), the curves, the model, metrics and report.

What the ranks share and how (``fwk.engine.fit`` and its callbacks):

* the batches: each rank takes every N-th sample of the epoch's permutation (a function of
  (seed, epoch): ``EpochSampler``), ``batch_size`` samples a step, so the *effective* batch is
  ``devices x batch_size`` and the gradient is the average over it (DDP averages the ranks'
  gradients of their mean losses); a set of n samples not divisible by N is padded by wrapping
  around the permutation;
* initial weights: every rank builds the same (seeded) network, and DDP broadcasts rank 0's;
* sampling noise (a VAE's reparameterisation, dropout): with several ranks every epoch draws
  from generators seeded by (seed, epoch, rank), so ranks draw different noise and a resumed
  run draws what an uninterrupted one did;
* the recorded losses (curves, the stopping rule): each rank's epoch means averaged over the
  ranks, so every rank makes the same early-stopping decision;
* threads: each rank registers as an fwk process (``fwk.engine.threads``); an executor's CPU
  allocation (``FWK_ALLOCATED_CPUS``) is split among the ranks.

One machine only: the ranks are processes of this machine (``LightningEnvironment``, whatever
a scheduler's variables say); several machines share work through a grid on Ray
(docs/scaling.md).
"""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from ..errors import FwkError
from .threads import ENV_ALLOCATED

#: the environment variable Lightning's launcher reads and sets; restored after each training
DIST_ENV = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE", "OMP_NUM_THREADS")

_JOB: dict | None = None  # in a rank process: the training it joins


class RankDone(BaseException):
    """Raised in a rank > 0 process when its training has ended (not an Exception: no task
    code catches it on its way out)."""


def rank_job() -> dict | None:
    """In a rank > 0 process, the training it is to join ({run_dir, ckdir, ckpt, ...}); else None."""
    return _JOB


def join(job: dict | None) -> None:
    """In a rank > 0 process (``fwk.rank``), before it reruns the task: the training to join
    (None: none, this process is no rank)."""
    global _JOB
    _JOB = job


def wants_ddp(config) -> bool:
    """Whether ``config`` (a TrainConfig) asks for fwk's DDP launcher: ``strategy: ddp``."""
    return isinstance(config.strategy, str) and config.strategy == "ddp"


def run_root(run_dir: Path) -> Path:
    """The nearest folder at or above ``run_dir`` holding a ``recipe.yaml`` (a sub-run of
    ``edit`` has none of its own; a grid member has)."""
    for d in [Path(run_dir), *Path(run_dir).parents]:
        if (d / "recipe.yaml").exists():
            return d
    raise FwkError(f"train.strategy ddp: {run_dir} is not inside a run directory with a recipe.yaml "
                   "(DDP ranks rerun the run's recipe; start it with fwk run)")


def make_job(ctx, ckdir: Path, ckpt: Path | None) -> dict:
    """What a rank process needs to rebuild the run up to this training."""
    return {"run_dir": str(run_root(ctx.run_dir).resolve()), "source": ctx.source,
            "ckdir": str(Path(ckdir).resolve()), "ckpt": str(ckpt) if ckpt else None,
            "cache": str(Path(ctx.cache.root).resolve()), "cache_enabled": bool(ctx.cache.enabled),
            "device": ctx.device}


def die_with_parent() -> None:
    """In a child process before it runs (Linux): be killed when its parent dies, however it
    dies (``kill -9`` included): a DDP rank rather than wait in a collective for the process
    group's timeout, a side-by-side fit (``fwk.sidebyside``) rather than train on alone, a grid
    member in a Ray worker (``fwk_grid.executors``) rather than write on into a killed grid's run."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the observer and Lightning's kill on error remain


class _Observer(threading.Thread):
    """Watches the rank processes while rank 0 trains: one that dies with an error leaves rank 0
    waiting in a collective, so this ends the process with a line that says which."""

    def __init__(self, procs):
        super().__init__(daemon=True, name="fwk-ddp-observer")
        self.procs, self.done = procs, threading.Event()

    def run(self):
        while not self.done.wait(1.0):
            for rank, p in enumerate(self.procs, start=1):
                code = p.poll()
                if code not in (None, 0):
                    print(f"fwk: DDP rank {rank} (pid {p.pid}) exited with code {code}; stopping the training "
                          "(its error is above; fwk run --resume continues from the last checkpoint)",
                          file=sys.stderr, flush=True)
                    for q in self.procs:
                        if q.poll() is None:
                            q.kill()
                    os._exit(1)  # rank 0 may sit in a collective that never returns


def sparse_state(module) -> list[str]:
    """The names of ``module``'s sparse parameters and buffers."""
    import torch  # deferred: loaded already wherever a module exists

    return [n for n, t in [*module.named_parameters(), *module.named_buffers()] if t.layout != torch.strided]


def make_strategy(job: dict, devices, world: int):
    """The Lightning strategy of fwk's DDP: ``DDPStrategy`` on this machine whose launcher
    starts ranks 1..world-1 as ``python -m fwk.rank JOB``."""
    # deferred like every Lightning import of the engine (see fwk.engine.trainer.fit)
    from lightning.fabric.plugins.environments import LightningEnvironment
    from lightning.pytorch.strategies import DDPStrategy
    from lightning.pytorch.strategies.launchers.subprocess_script import _SubprocessScriptLauncher
    from torch.nn.parallel import DistributedDataParallel

    class Launcher(_SubprocessScriptLauncher):
        """Lightning's subprocess launcher with fwk's rank command and observer."""

        observer: _Observer | None = None

        def launch(self, function, *args, trainer=None, **kwargs):
            self.cluster_environment.validate_settings(num_devices=self.num_processes, num_nodes=self.num_nodes)
            if not self.cluster_environment.creates_processes_externally:
                self._spawn()
                self.observer = _Observer(self.procs)
                self.observer.start()
            try:
                return function(*args, **kwargs)
            finally:
                if self.observer is not None:
                    self.observer.done.set()

        def _spawn(self):
            env = self.cluster_environment
            os.environ["MASTER_ADDR"] = env.main_address
            os.environ["MASTER_PORT"] = str(env.main_port)
            os.environ["NODE_RANK"] = "0"
            os.environ["LOCAL_RANK"] = "0"
            os.environ["WORLD_SIZE"] = str(self.num_processes)
            self.procs = []
            cmd = [sys.executable, "-m", "fwk.rank", json.dumps(job)]
            for rank in range(1, self.num_processes):
                self.procs.append(subprocess.Popen(cmd, env={**os.environ, "LOCAL_RANK": str(rank)},
                                                   preexec_fn=die_with_parent))

    class FwkDDP(DDPStrategy):
        """DDP on this machine's processes, ranks started by fwk (``python -m fwk.rank``)."""

        def _configure_launcher(self):
            self._launcher = Launcher(self.cluster_environment, self.num_processes, self.num_nodes)

        def _setup_model(self, model):
            # sparse buffers (the samplers' pooling matrices) cannot be broadcast; every rank
            # builds them identically from the same template, so DDP leaves them alone
            DistributedDataParallel._set_params_and_buffers_to_ignore_for_model(model, sparse_state(model))
            return super()._setup_model(model)

    # a strategy instance keeps its own checkpoint IO (Lightning's default pickles): fwk's safe one
    from .callbacks import SafeCheckpointIO
    return FwkDDP(cluster_environment=LightningEnvironment(), checkpoint_io=SafeCheckpointIO())


class DistEnv:
    """Context manager around a DDP training in rank 0: the environment variables the launcher
    sets are restored, an executor's CPU allocation is split among the ranks, and the process
    group is taken down at the end, so the next training (DDP or not) starts clean."""

    def __init__(self, world: int):
        self.world = world

    def __enter__(self):
        self.saved = {k: os.environ.get(k) for k in (*DIST_ENV, ENV_ALLOCATED)}
        alloc = os.environ.get(ENV_ALLOCATED)
        if alloc and alloc.strip().isdigit():
            os.environ[ENV_ALLOCATED] = str(max(1, int(alloc) // self.world))
        return self

    def __exit__(self, *exc):
        import torch.distributed as dist  # deferred: torch is loaded already where this runs

        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        return False
