"""A run's seeds side by side (``fwk.seeds.seed_rounds``) against one after another, on a recipe
whose models are unbalanced as chapter 4's k = 50 seeds study is (a long network beside a short
one: there one seed's long model trained alone while the second core idled).

    python benchmarks/seeds_side_by_side.py [--epochs 30] [--vertices 2000]

A reconstruct recipe on synthetic-heads (``--vertices``, 40 subjects) with two autoencoders, a
wide one (channels [16, 32, 64]) and a narrow one ([4]), ``seeds: [0, 1, 2]``, run twice with 2
threads, each with an empty cache, in a fresh run directory, after a small warm-up run of each
(imports and first calls):

* ``in turn``: the seeds one after another, each seed's two models side by side with a thread
  each (fwk before seeds ran side by side: ``fwk.runs.SEEDS_ONE_AFTER_ANOTHER``);
* ``side by side``: seeds 0 and 1 in two processes with a thread each (their models one after
  another), then seed 2 alone with its models side by side.

Every model trains with one thread either way; the script checks that both runs' models are the
same bit for bit and prints both wall times and their ratio. Run it on an otherwise idle machine
(the load average is printed). The last line is one JSON object with the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml


def recipe(epochs: int, vertices: int) -> dict:
    ae = {"name": "ae", "sampler": {"name": "quadric", "factors": [4, 4, 4]}}
    return {"name": "seeds-sbs", "task": "reconstruct", "seed": 0, "seeds": [0, 1, 2],
            "dataset": {"name": "synthetic-heads", "n_vertices": vertices, "n_subjects": 40},
            "split": {"ratios": [0.7, 0.1, 0.2]}, "train": {"epochs": epochs, "batch_size": 8},
            "models": {"wide": {**ae, "channels": [16, 32, 64], "latent": 32},
                       "narrow": {**ae, "channels": [4], "latent": 8, "sampler": {"name": "quadric", "factors": [4]}}},
            "metrics": ["l1"], "renders": 0}


def run(r: dict, root: Path, in_turn: bool) -> tuple[float, Path]:
    import fwk.runs as runs

    d = root / ("in-turn" if in_turn else "side-by-side")
    d.mkdir()
    (d / "r.yaml").write_text(yaml.safe_dump(r))
    os.environ["FWK_CACHE"] = str(d / "cache")
    runs.SEEDS_ONE_AFTER_ANOTHER[0] = in_turn  # the run resets it as it ends
    t0 = time.perf_counter()
    out = runs.execute(str(d / "r.yaml"), runs_dir=str(d / "runs"), quiet=True)
    return time.perf_counter() - t0, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--vertices", type=int, default=2000)
    a = ap.parse_args()
    os.environ["FWK_THREADS"] = "2"
    from fwk.safeio import load_state

    r = recipe(a.epochs, a.vertices)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        os.environ["FWK_RUNTIME_DIR"] = str(root / "procs")
        warm = root / "warm-up"
        warm.mkdir()
        run({**recipe(1, 300), "seeds": [0, 1]}, warm, True)  # imports and first-call costs, not timed
        run({**recipe(1, 300), "seeds": [0, 1]}, warm, False)
        t_turn, run_turn = run(r, root, True)
        t_sbs, run_sbs = run(r, root, False)
        same = True
        for s in r["seeds"]:
            for p in sorted((run_turn / f"seed-{s}" / "models").glob("*.safetensors")):
                a_, b_ = load_state(p), load_state(run_sbs / f"seed-{s}" / "models" / p.name)
                same &= all(torch.equal(a_[k], b_[k]) for k in a_ if isinstance(a_[k], torch.Tensor))
    print(f"seeds in turn {t_turn:.1f} s, side by side {t_sbs:.1f} s: {t_turn / t_sbs:.2f}x; "
          f"models the same bit for bit: {same}; load average {load0:.2f} -> {os.getloadavg()[0]:.2f}")
    print(json.dumps({"in_turn_s": t_turn, "side_by_side_s": t_sbs, "ratio": t_turn / t_sbs, "same_models": same,
                      "epochs": a.epochs, "vertices": a.vertices, "load": [load0, os.getloadavg()[0]]}))


if __name__ == "__main__":
    sys.exit(main())
