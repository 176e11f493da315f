"""Two trainings side by side with a thread each against one after another with both threads
(issue 28, item 3; ``fwk.sidebyside``, ``train.side_by_side``), per network.

    python benchmarks/side_by_side.py [--steps 10] [--rounds 2] [--only NAME ...]

For each network (batch 16, on the face-head of ``_ict.face_head``: ICT-FaceKit's 11,248
vertices when present, else a synthetic head of that size):

* ``together``: one process with 2 torch threads runs ``steps`` training steps (forward, L1,
  backward, Adam; ``training.stepper``) after a warm-up step: t2 a step;
* ``side by side``: two processes forked from it (as ``fwk.sidebyside`` forks), each with 1
  thread and its own copy of the network, warm up, wait for each other, then run ``steps``
  steps each at the same time: W the wall time from the first start to the last end.

The gain of fitting two models side by side is the steps per second of both children over those of
one process with both threads, ``2 steps t2 / W`` (above 1: side by side is faster). Rounds
alternate the two modes; the medians are printed, with the load average. Networks: the main
job's PB network (spiral++ VAE [8, 16, 32], latent 16; it runs on ~6k vertices there), the
chapter 5 width vcconv VAE, the thesis-width vcconv VAE and the spiral++ AE of
``benchmarks/training.py``. The last line is one JSON object with every figure.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _ict import face_head  # noqa: E402
from training import MAIN_JOB_PB, SPIRALPP_AE, VCCONV_VAE, VCCONV_VAE_CH5, BATCH, networks, stepper  # noqa: E402

NETWORKS = {"main job PB": MAIN_JOB_PB, "vcconv ch5": VCCONV_VAE_CH5, "vcconv VAE": VCCONV_VAE,
            "spiral++ AE": SPIRALPP_AE}


def _build(spec, t, x_np):
    torch.manual_seed(0)
    enc, dec, _ = networks(spec, t)
    return stepper(enc, dec, torch.from_numpy(x_np))


def _child(spec, t, x_np, steps, barrier, out):
    torch.set_num_threads(1)
    step = _build(spec, t, x_np)
    step()  # warm-up
    barrier.wait()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    out.put((t0, time.perf_counter()))


def together(spec, t, x_np, steps) -> float:
    torch.set_num_threads(2)
    step = _build(spec, t, x_np)
    step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return (time.perf_counter() - t0) / steps


def side_by_side(spec, t, x_np, steps) -> float:
    ctx = mp.get_context("fork")
    barrier, out = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_child, args=(spec, t, x_np, steps, barrier, out)) for _ in range(2)]
    for p in procs:
        p.start()
    spans = [out.get() for _ in procs]
    for p in procs:
        p.join()
        if p.exitcode:
            raise SystemExit(f"a side-by-side child failed (exit {p.exitcode})")
    return max(e for _, e in spans) - min(s for s, _ in spans)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=None, choices=list(NETWORKS))
    a = ap.parse_args()
    col, what = face_head(1)
    t = col.template
    x_np = np.random.default_rng(0).standard_normal((BATCH, t.n_vertices, 3)).astype(np.float32)
    print(f"{what}: {t.n_vertices} vertices, batch {BATCH}, {a.steps} steps, {a.rounds} rounds, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'network':<13} {'2 threads ms/step':>18} {'side by side ms/step':>21} {'gain':>6}")
    rows = {}
    for name in a.only or NETWORKS:
        spec = NETWORKS[name]
        t2, W = [], []
        for _ in range(a.rounds):
            t2.append(together(spec, t, x_np, a.steps))
            W.append(side_by_side(spec, t, x_np, a.steps))
        t2m, Wm = float(np.median(t2)), float(np.median(W))
        gain = 2 * a.steps * t2m / Wm
        rows[name] = {"together_ms": 1e3 * t2m, "side_by_side_ms_per_step_each": 1e3 * Wm / a.steps, "gain": gain}
        print(f"{name:<13} {1e3 * t2m:>18.0f} {1e3 * Wm / a.steps:>21.0f} {gain:>6.2f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")
    print(json.dumps({"vertices": t.n_vertices, "steps": a.steps, "rounds": a.rounds, "rows": rows}))


if __name__ == "__main__":
    main()
