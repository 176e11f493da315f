"""Shared by the benchmarks: the ICT-FaceKit face-head region (11,248 vertices), or a
synthetic head of the same size when the data is absent; timing helpers."""
from __future__ import annotations

import numpy as np


def face_head(n_subjects: int = 2):
    from fwk.cache import Cache
    from fwk.plugins import get_registry
    from fwk.testing import ict_path

    reg = get_registry()
    folder = ict_path()
    if folder is not None:
        col = reg.get("dataset", "ict-facekit")(path=str(folder), n_subjects=n_subjects).load(Cache())
        return col, "ict-facekit face-head"
    col = reg.get("dataset", "synthetic-heads")(n_subjects=n_subjects, n_vertices=11248).load(Cache())
    return col, "synthetic-heads (ICT data not found)"


def timeit(fn, repeat: int = 7) -> float:
    import time

    fn()
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def alternate(fns: dict, n: int, cpu: bool = False) -> dict:
    """Median seconds per call of each closure, called in turn n times after one warm-up each
    (side by side: a load that comes and goes falls on every version alike).

    ``cpu``: the process's CPU seconds (``time.process_time``) instead of wall seconds. With one
    compute thread this is the work itself, without the time the scheduler gave to other
    processes: on this shared 2-core machine, loaded by trainings, wall-clock A/B ratios of one
    pair of networks swung 0.74-1.63x between runs, CPU-time ratios 1.00-1.11x (2026-12-05). It
    counts every thread's CPU time, so it is no wall time with more threads (``benchmarks/
    training.py --cpu-time`` refuses them)."""
    import time

    clock = time.process_time if cpu else time.perf_counter
    for f in fns.values():
        f()
    ts = {k: [] for k in fns}
    for _ in range(n):
        for k, f in fns.items():
            t0 = clock()
            f()
            ts[k].append(clock() - t0)
    return {k: float(np.median(v)) for k, v in ts.items()}
