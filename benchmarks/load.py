"""Steady under outside load (issue 25): a vcconv VAE training step and the eigenbasis, alone and
beside a 2-thread compute process that is not fwk's, side by side in one run.

    python benchmarks/load.py [--steps 5] [--rounds 2] [--k 500] [--skip-eig] [--before] [--private-registry]

Run it with no thread variables set (``FWK_THREADS``, ``OMP_NUM_THREADS``, ``OMP_WAIT_POLICY``,
...): fwk's defaults then apply, as in a training:

* how idle threads wait: ``import fwk`` comes first here, so its wait policy (``fwk._waiting``)
  is set before torch and NumPy load;
* how many threads: at the start of each phase the script does what ``fit`` does when a run
  starts, ``fwk.engine.threads.apply_threads()`` after a fresh load window (the rule: the cores
  left free by other work, shared by the live fwk processes), and prints the count and why.

The other process is a NumPy matmul loop (1024 x 1024, float64) started with
``OMP_NUM_THREADS=OPENBLAS_NUM_THREADS=MKL_NUM_THREADS=2`` and the user's environment without
what fwk added (so it waits as any non-fwk program does); it is paused (SIGSTOP) during the
"alone" phases and resumed for the "beside" ones, alternating for ``--rounds`` rounds.

* ``vcconv VAE``: ``benchmarks/training.py``'s network and step (forward, L1, backward, Adam;
  batch 16) on the ICT-FaceKit face-head region (11,248 vertices; a synthetic head of the same
  size where ICT-FaceKit is absent, printed); median step time of ``--steps`` after a warm-up;
* ``eigenbasis``: ``fwk.geometry.spectral.generalized_eigs`` of the cotangent Laplacian and
  Voronoi mass matrix of the same mesh, k = 500 (``benchmarks/geometry.py``'s timing).

Also printed: the CPU the idle thread pools burn (torch's OpenMP and NumPy's OpenBLAS, 2 threads
each, sleeping 2 / 20 ms between products; ``probe_idle_cpu``) in child processes, with fwk's
defaults and with the pre-issue-25 waiting (``GOMP_SPINCOUNT=300000``,
``OPENBLAS_THREAD_TIMEOUT=28``), which verifies that the wait policy takes effect; the
1-minute load average at the start and end; the share of a CPU the other process got.
``--before`` reruns the timings in a child process with the pre-issue-25 defaults (those
waiting variables, and ``FWK_THREADS`` = the cores: threads by fwk processes only), for
comparison. ``--private-registry`` keeps the fwk processes of other users of a shared machine
out of the count of live fwk processes (they then count by the CPU they use, as outside load).
The last line is one JSON object with every figure.
"""
from __future__ import annotations

import fwk  # noqa: F401  first: fwk's wait policy, before torch and NumPy load
from fwk import _waiting

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import training  # noqa: E402
from _ict import face_head  # noqa: E402
from fwk.engine import threads  # noqa: E402
from fwk.geometry.operators import cotangent_laplacian, mass_matrix  # noqa: E402
from fwk.geometry.spectral import generalized_eigs  # noqa: E402

THREAD_VARS = ("FWK_THREADS", "FWK_ALLOCATED_CPUS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
               "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OPENBLAS_THREAD_TIMEOUT", "GOTO_THREAD_TIMEOUT", "KMP_BLOCKTIME")
#: the waiting before issue 25 (libgomp's and OpenBLAS's own defaults), set explicitly
BEFORE = {"GOMP_SPINCOUNT": "300000", "OPENBLAS_THREAD_TIMEOUT": "28"}

MATMUL_LOOP = """
import numpy as np
a = np.random.default_rng(0).random((1024, 1024))
a @ a
print("ready", flush=True)
while True:
    a @ a
"""

IDLE_CPU = """
import sys, time
if sys.argv[1] == "fwk":
    import fwk
if sys.argv[2] == "torch":
    import torch
    torch.set_num_threads(2)
    a = torch.randn(256, 256)
    work, gap = (lambda: torch.mm(a, a)), 0.002
else:
    import numpy as np
    a = np.random.rand(512, 512)
    work, gap = (lambda: a @ a), 0.02
work()
cpu = wall = 0.0
for _ in range(50):
    work()
    c0, w0 = time.process_time(), time.perf_counter()
    time.sleep(gap)
    cpu += time.process_time() - c0
    wall += time.perf_counter() - w0
print(cpu / wall)
"""


def foreign_env() -> dict:
    """The environment of a program that is not fwk: the user's, without what fwk added."""
    env = {k: v for k, v in os.environ.items() if k not in _waiting.added}
    env.update(OMP_NUM_THREADS="2", OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")
    return env


def probe_idle_cpu(lib: str, env: dict) -> float:
    """Cores a child process burns while its 2-thread pool (torch's or NumPy's) sits idle."""
    env = {**env, "OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", IDLE_CPU, "fwk", lib], env=env, capture_output=True, text=True,
                         check=True)
    return float(out.stdout.strip().splitlines()[-1])


class Other:
    """The non-fwk compute process, paused or running. Started through ``sh ... &`` so that it is
    not a child of this process (fwk counts its own processes' children as fwk's work)."""

    def __init__(self):
        self.sh = subprocess.Popen(["sh", "-c", '"$0" -c "$1" & echo $!', sys.executable, MATMUL_LOOP],
                                   env=foreign_env(), stdout=subprocess.PIPE, text=True)
        self.pid = int(self.sh.stdout.readline())
        assert self.sh.stdout.readline().strip() == "ready"
        self.sh.wait()
        self.pause()

    def ticks(self) -> int:
        st = threads._proc_stat(Path(f"/proc/{self.pid}/stat"))
        return st[3] if st else 0

    def pause(self):
        os.kill(self.pid, signal.SIGSTOP)

    def resume(self):
        os.kill(self.pid, signal.SIGCONT)

    def close(self):
        os.kill(self.pid, signal.SIGKILL)
        self.sh.stdout.close()


def run_start(settle: float) -> tuple[int, str]:
    """What fit does when a run starts, after a fresh load window of ``settle`` seconds."""
    time.sleep(settle)  # the other process ramps up (or its last burst fades)
    threads.outside_load()  # a fresh window starts now
    time.sleep(0.5)
    n, why, _ = threads.apply_threads()
    return n, why


def timed(fn, repeat: int, warm: bool = True) -> float:
    if warm:
        fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def measure(name, fn, repeat, warm, other, rounds, settle, result):
    """``rounds`` x (alone, beside); prints one line a phase; records medians and the ratio."""
    rows = {"alone": [], "beside": []}
    hz = os.sysconf("SC_CLK_TCK")
    for r in range(rounds):
        for phase in ("alone", "beside"):
            (other.resume if phase == "beside" else other.pause)()
            n, why = run_start(settle)
            t0, k0 = time.perf_counter(), other.ticks()
            s = timed(fn, repeat, warm)
            share = (other.ticks() - k0) / hz / (time.perf_counter() - t0)
            rows[phase].append({"s": s, "threads": n, "why": why, "other_cpu": share,
                                "load_avg": os.getloadavg()[0]})
            print(f"{name:<11} round {r + 1} {phase:<6} {1e3 * s:>9.0f} ms  threads {n} ({why}); "
                  f"other process {share:.2f} CPU; load average {os.getloadavg()[0]:.2f}", flush=True)
    other.pause()
    alone = float(np.median([x["s"] for x in rows["alone"]]))
    beside = float(np.median([x["s"] for x in rows["beside"]]))
    result[name] = {"alone_ms": 1e3 * alone, "beside_ms": 1e3 * beside, "ratio": beside / alone, "phases": rows}
    return alone, beside


def timings(a) -> dict:
    torch.manual_seed(0)
    col, src = face_head(1)
    t = col.template
    x = torch.randn(training.BATCH, t.n_vertices, 3)
    enc, dec, _ = training.networks(training.VCCONV_VAE, t)
    step = training.stepper(enc, dec, x)
    result = {"template": src, "n_vertices": t.n_vertices, "cores": threads.available_cores(),
              "wait": {k: os.environ.get(k) for k in THREAD_VARS if k in os.environ},
              "fwk_added": dict(_waiting.added), "load_average_start": os.getloadavg()[0]}
    print(f"template: {src}, {t.n_vertices} vertices; {result['cores']} cores; torch {torch.__version__}; "
          f"waiting: {result['wait']}; load average {result['load_average_start']:.2f}", flush=True)
    threads.register()
    other = Other()
    try:
        measure("vcconv VAE", step, a.steps, True, other, a.rounds, a.settle, result)
        if not a.skip_eig:
            V, F = t.vertices, t.triangles
            L, M = cotangent_laplacian(V, F).tocsc(), mass_matrix(V, F).tocsc()
            measure("eigenbasis", lambda: generalized_eigs(L, M, a.k), 1, False, other, a.rounds, a.settle, result)
    finally:
        other.close()
    result["load_average_end"] = os.getloadavg()[0]
    return result


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=5, help="timed VAE steps per phase (after one warm-up)")
    ap.add_argument("--rounds", type=int, default=2, help="(alone, beside) rounds of each timing")
    ap.add_argument("--k", type=int, default=500, help="eigenvectors of the eigenbasis")
    ap.add_argument("--settle", type=float, default=1.0, help="seconds after pausing or resuming the other process")
    ap.add_argument("--skip-eig", action="store_true")
    ap.add_argument("--before", action="store_true",
                    help="also time with the waiting and thread rule from before issue 25, in a child process")
    ap.add_argument("--private-registry", action="store_true",
                    help="register in a folder of its own (FWK_RUNTIME_DIR): other fwk processes on a shared machine "
                         "then count by the CPU they use, like any other work, not as live fwk processes")
    ap.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.private_registry:
        import tempfile

        os.environ[threads.ENV_RUNTIME_DIR] = tempfile.mkdtemp(prefix="fwk-load-")
    set_ = [k for k in THREAD_VARS if k in os.environ and k not in _waiting.added]
    if set_ and not a.json_only:
        print(f"note: {', '.join(set_)} set: fwk's defaults do not fully apply", flush=True)
    out = {}
    if not a.json_only:
        fwk_env = dict(os.environ)
        before_env = {**foreign_env(), **BEFORE}
        out["idle_cpu"] = {lib: {"fwk": probe_idle_cpu(lib, fwk_env), "before": probe_idle_cpu(lib, before_env)}
                           for lib in ("torch", "numpy")}
        for lib, v in out["idle_cpu"].items():
            print(f"idle {lib} pool (2 threads): {v['fwk']:.2f} CPU burnt while idle with fwk's waiting, "
                  f"{v['before']:.2f} with the waiting before issue 25", flush=True)
    out.update(timings(a))
    for name in ("vcconv VAE", "eigenbasis"):
        if name in out:
            r = out[name]
            print(f"{name}: alone {r['alone_ms']:.0f} ms, beside {r['beside_ms']:.0f} ms: {r['ratio']:.1f}x", flush=True)
    if a.before:
        env = {**foreign_env(), **BEFORE, "FWK_THREADS": str(threads.available_cores())}
        for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env.pop(k, None)
        args = [sys.executable, __file__, "--json-only", "--steps", str(a.steps), "--rounds", str(a.rounds),
                "--k", str(a.k), "--settle", str(a.settle)] + (["--skip-eig"] if a.skip_eig else []) + (
                ["--private-registry"] if a.private_registry else [])
        print("before issue 25 (GOMP_SPINCOUNT=300000, OPENBLAS_THREAD_TIMEOUT=28, FWK_THREADS=cores):", flush=True)
        proc = subprocess.run(args, env=env, stdout=subprocess.PIPE, text=True, check=True)
        lines = proc.stdout.strip().splitlines()
        for line in lines[:-1]:
            print(f"  {line}", flush=True)
        out["before"] = json.loads(lines[-1])
    out["load_average_end"] = os.getloadavg()[0]
    print(f"load average at start / end: {out['load_average_start']:.2f} / {out['load_average_end']:.2f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
