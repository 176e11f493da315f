"""Chunks of one layer spread over torch's threads without an OpenMP barrier per small op.

``in_workers(work, workers)`` runs ``work(w)`` for w in 0..workers-1: w = 0 on the calling
thread, the others on one process-wide thread pool, every torch op inside single-threaded. The
chunked convs (spiral++'s ``GatherLinear``, feast's plans) deal their chunks round-robin to
the workers this way rather than letting each small op fan out over OpenMP: one join per call
instead of a barrier per op, which stalls whenever another process holds a core (measured on
the spiral++ AE: 3.6 s against 0.9 s a step on one thread under outside load). torch's thread
count is restored afterwards. Only the plugins that train import this module (it imports torch).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import torch

_POOL: list = []  # one ThreadPoolExecutor, made on first use, grown when more workers are asked for


def in_workers(work, workers: int) -> None:
    """Run ``work(w)`` for w in 0..workers-1 (see the module docstring); exceptions propagate."""
    if workers <= 1:
        work(0)
        return
    if not _POOL or _POOL[0]._max_workers < workers - 1:
        _POOL[:] = [ThreadPoolExecutor(max_workers=workers - 1, thread_name_prefix="fwk-workers")]

    def run(w):
        torch.set_num_threads(1)  # this pool thread's ops (and MKL's, process-wide until restored)
        with torch.no_grad():  # grad mode is per thread; the work is a Function's forward or backward
            work(w)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        futures = [_POOL[0].submit(run, w) for w in range(1, workers)]
        work(0)
        for f in futures:
            f.result()
    finally:
        torch.set_num_threads(threads)
