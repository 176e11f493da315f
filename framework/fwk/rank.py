"""A DDP rank > 0 process: ``python -m fwk.rank JOB`` (started by ``fwk.engine.distributed``'s
launcher, never by hand).

The rank reopens the run directory rank 0 is writing (its ``recipe.yaml``), reruns the task in
resume mode with its output silenced (data from the cache, finished models and trainings
loaded, nothing retrained), joins rank 0 in the one training named by JOB
(``fwk.engine.distributed.join``) and exits when that training ends (``RankDone``).

It lives above ``fwk.runs`` rather than in the engine: the engine trains modules and knows
nothing of run directories and tasks, so ``fwk.runs`` may import the engine and never the
reverse (``tests/architecture/test_architecture.py``, the layers).
"""
from __future__ import annotations

import json
import os
import sys
import traceback
from pathlib import Path

from .cache import Cache
from .engine.distributed import RankDone, join
from .errors import FwkError
from .plugins import get_registry
from .recipes import read_recipe_file, resolve
from .runs import RunContext, run_task


def main(argv: list[str]) -> int:
    """Rebuild the run of ``argv[0]`` (a job of ``fwk.engine.distributed.make_job``, as JSON) in
    resume mode and join its training; 0 when the training ended, 1 otherwise."""
    job = json.loads(argv[0])
    rank = os.environ.get("LOCAL_RANK", "?")
    join(job)
    try:
        run_dir = Path(job["run_dir"])
        data = read_recipe_file(run_dir / "recipe.yaml", "run recipe")  # every check of a recipe file
        if job.get("source") and not data.get("source"):
            data["_source"] = job["source"]
        registry = get_registry()
        resolved = resolve(data, registry)
        ctx = RunContext(run_dir, registry, Cache(job["cache"], enabled=job["cache_enabled"]), resolved.seed,
                         recipe=resolved.data, train=resolved.train, device=job["device"], quiet=True,
                         resume=True, log_file=Path(os.devnull))
        ctx.source = resolved.source
        run_task(resolved, ctx)
    except RankDone:
        return 0
    except FwkError as exc:  # a user's error (a recipe.yaml refused, a damaged file): its one line
        print(f"fwk DDP rank {rank}: {exc}", file=sys.stderr, flush=True)
        return 1
    except Exception:
        print(f"fwk DDP rank {rank}: {traceback.format_exc()}", file=sys.stderr, flush=True)
        return 1
    finally:
        join(None)  # this process is a rank only while main runs (a caller in-process, a test, goes on as itself)
    print(f"fwk DDP rank {rank}: the run ended without reaching the training of {job['ckdir']}",
          file=sys.stderr, flush=True)
    return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
