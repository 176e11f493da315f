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

``fwk.forked.run_forked`` is the machinery (jobs in forked children, w at a time, outcomes back as JSON);
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

from .forked import run_or_raise  # the machinery, below the runs layer: the seeds share it


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
    outcomes = run_or_raise(jobs, ctx, workers, threads, why, "model")
    return {label: float(out["seconds"]) for label, out in outcomes.items()}
