"""A 2-member grid on this machine's cores: members in turn (``executor: local`` with
``train.side_by_side=false``, each member taking every core), side by side in processes forked by
the local executor (its default, ``fwk.sidebyside``: one thread each) and side by side on Ray
(``executor: ray``, one CPU and one thread each), the three wall times measured in one go.

    python benchmarks/grid_scaling.py                       # spiral-euclidean, spiral-dr; 20 epochs
    python benchmarks/grid_scaling.py --epochs 40 --members spiral-euclidean lsa-dr

The members are configurations of ``recipes/smoke/grid.yaml`` (merged on its ``grid_base.yaml``)
with ``train.epochs`` set; each ``fwk run`` is a fresh process with ``FWK_THREADS`` and
``OMP_NUM_THREADS`` removed from its environment (so fwk's own rule sizes the threads: one
process alone takes every core, a Ray member its allocation), its cache warmed by a first
untimed run, its runs folder a temporary one, and its registry of live fwk processes its own
(``FWK_RUNTIME_DIR``: other jobs' fwk processes do not change its thread counts). Prints the load average before and after
(other work on the machine slows both and skews the comparison) and both members' metrics
agree between the executors only up to the thread count's rounding (2 threads against 1).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
GRID = REPO / "recipes" / "smoke" / "grid.yaml"


def write_grid(folder: Path, members: list[str], epochs: int) -> Path:
    """A grid of ``members`` (configurations of the smoke grid) on its base, ``epochs`` each."""
    smoke = yaml.safe_load(GRID.read_text())
    missing = [m for m in members if m not in smoke["configs"]]
    if missing:
        sys.exit(f"--members: {', '.join(missing)} not in {GRID} (there: {', '.join(smoke['configs'])})")
    configs = {m: {**smoke["configs"][m], "train": {"epochs": epochs}} for m in members}
    path = folder / "scaling.yaml"
    path.write_text(yaml.safe_dump({"task": "grid", "base": str(GRID.parent / smoke["base"]), "configs": configs},
                                   sort_keys=False))
    return path


def run(recipe: Path, runs: Path, env: dict, *overrides: str) -> float:
    """Wall seconds of one ``fwk run`` (quiet); exits on failure."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "fwk", "--quiet", "run", str(recipe), *overrides, "--runs-dir", str(runs)],
                       env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(p.stdout[-2000:] + p.stderr[-2000:])
    return wall


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", nargs=2, default=["spiral-euclidean", "spiral-dr"])
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--cache", default=None, help="FWK_CACHE for the runs (default: a temporary folder)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fwk-grid-scaling-") as tmp:
        tmp = Path(tmp)
        env = {k: v for k, v in os.environ.items() if k not in ("FWK_THREADS", "OMP_NUM_THREADS")}
        env["FWK_CACHE"] = args.cache or str(tmp / "cache")
        env["RAY_USAGE_STATS_ENABLED"] = "0"
        # a registry of live fwk processes of its own: fwk processes of other jobs on a shared
        # machine would otherwise take threads from the members in turn (fwk.engine.threads)
        env["FWK_RUNTIME_DIR"] = str(tmp / "procs")
        recipe = write_grid(tmp, args.members, args.epochs)
        (tmp / "warm").mkdir()
        warm = write_grid(tmp / "warm", args.members, 1)
        run(warm, tmp / "warm-runs", env)  # the data, samplers and operators into the cache
        load0 = os.getloadavg()
        local = run(recipe, tmp / "local", env, "train.side_by_side=false")
        forked = run(recipe, tmp / "forked", env)
        ray = run(recipe, tmp / "ray", env, "executor=ray")
        load1 = os.getloadavg()
        cores = len(os.sched_getaffinity(0))
        print(f"{cores} cores; members {', '.join(args.members)}, {args.epochs} epochs each")
        print(f"load average before {load0[0]:.2f} / {load0[1]:.2f} / {load0[2]:.2f}, "
              f"after {load1[0]:.2f} / {load1[1]:.2f} / {load1[2]:.2f}")
        print(f"in turn (executor local, train.side_by_side=false, {cores} threads each): {local:.1f} s")
        print(f"side by side, forked (executor local, 1 thread each): {forked:.1f} s ({forked / local:.2f} of in turn)")
        print(f"side by side (executor ray, 1 CPU and 1 thread each): {ray:.1f} s ({ray / local:.2f} of in turn)")
        (d_local,), (d_forked,), (d_ray,) = (list((tmp / k).iterdir()) for k in ("local", "forked", "ray"))
        for m in args.members:
            a, c = (json.loads((d / m / "metrics.json").read_text())["models"]["ae"]["test"]["l1"]["mean"]
                    for d in (d_forked, d_ray))
            print(f"{m}: test L1 forked {a:.6g}, ray {c:.6g} (both one thread: equal {a == c})")
            a, b = (json.loads((d / m / "metrics.json").read_text())["models"]["ae"]["test"]["l1"]["mean"]
                    for d in (d_local, d_ray))
            ta, tb = ({h["threads"] for h in json.loads((d / m / "curves" / "ae" / "ae.json").read_text())["epochs"]}
                      for d in (d_local, d_ray))
            print(f"{m}: test L1 {a:.6g} in turn, {b:.6g} side by side (relative difference {abs(a - b) / a:.1e}); "
                  f"threads {sorted(ta)} in turn, {sorted(tb)} side by side")
    return 0


if __name__ == "__main__":
    sys.exit(main())
