"""Claim C4 (thesis 4.7.1, tables 4.2-4.4) from a finished chapter 4 run (issue 13).

    python benchmarks/claims_ch4.py RUN [--k KRUN] [--splits train,test]

RUN is a run of ``recipes/thesis/ch4/plateau.yaml`` (one reconstruct run: ``dsm`` and ``dsm-g04``,
the single-representation VAEs, SpiralNet++, Neural 3DMM and the mean shape); KRUN, optional, a
run of ``recipes/thesis/ch4/k-plateau.yaml`` (grid members ``k<k>``). Prints, in markdown:

* per split, one row per model: L1, DAME and FMPD (mean over meshes, evaluation space), whether
  the model is on the L1/DAME Pareto front of the learned models (the thesis's comparison: the
  mean shape is not in it), and its training: epochs, what ended it, the plateau rule's verdict
  and minutes (the sum of the epochs' own seconds, a resumed run's earlier epochs included);
* per dsm model and split, the C4 reading: on the front or not, its DAME rank and L1 rank among
  the learned models, and whether it beats the mean shape on both metrics. Thesis table 4.2:
  dsm had the lowest DAME on both data sets' training and test splits and was behind SpiralNet++
  and Neural 3DMM on L1 on 3 of the 4; C4 "holds" for a split when dsm is on the front with the
  lowest DAME, "partly" when it is on the front without it, "does not hold" off the front;
* with KRUN, the k study: L1, DAME, FMPD of dsm per k on each split, and the front over k.

No threshold is tuned: a comparison is the sign of a difference of means.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from fwk.evaluation.core import pareto_front

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import training  # noqa: E402

BASELINE = "mean-shape"


def load(run: Path) -> dict:
    """{label: {split: {metric: mean}, "training": {...}}} of the run's models."""
    m = json.loads((run / "metrics.json").read_text())
    return {label: {**{split: {k: v["mean"] for k, v in res.items()} for split, res in r.items()},
                    "training": training(m, label, run)}
            for label, r in m["models"].items()}


def reading(models: dict, split: str) -> tuple[list[str], dict]:
    """(the learned models on the L1/DAME front, {dsm label: its C4 reading}) on ``split``."""
    learned = [k for k in models if k != BASELINE and split in models[k]]
    pts = [(models[k][split]["l1"], models[k][split]["dame"]) for k in learned]
    front = [learned[i] for i in pareto_front(pts)]
    by_dame = sorted(learned, key=lambda k: models[k][split]["dame"])
    by_l1 = sorted(learned, key=lambda k: models[k][split]["l1"])
    base = models.get(BASELINE, {}).get(split)
    out = {}
    for k in learned:
        if not k.startswith("dsm"):
            continue
        on, best = k in front, by_dame[0] == k
        r = models[k][split]
        out[k] = {"front": on, "dame_rank": by_dame.index(k) + 1, "l1_rank": by_l1.index(k) + 1, "n": len(learned),
                  "beats_mean": None if base is None else bool(r["l1"] < base["l1"] and r["dame"] < base["dame"]),
                  "verdict": "holds" if on and best else ("partly" if on else "does not hold")}
    return front, out


def k_rows(krun: Path) -> list[tuple[int, dict]]:
    """(k, {split: {metric: mean}}) of the k study's finished members, by k."""
    rows = []
    for d in krun.iterdir():
        mk = re.fullmatch(r"k(\d+)", d.name)
        if mk and (d / "metrics.json").exists():
            models = load(d)
            dsm = next((v for k, v in models.items() if k.startswith("dsm")), None)
            if dsm is not None:
                rows.append((int(mk.group(1)), dsm))
    return sorted(rows, key=lambda r: r[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--k", type=Path, default=None, help="a run of recipes/thesis/ch4/k-plateau.yaml")
    ap.add_argument("--splits", default="train,test")
    a = ap.parse_args(argv)
    models = load(a.run)
    for split in a.splits.split(","):
        front, read = reading(models, split)
        print(f"\n{split} ({a.run.name}), evaluation space, mean over meshes\n")
        print("| model | L1 ×1e-3 | DAME ×1e-2 | FMPD ×1e-2 | on the L1/DAME front | epochs | ended by | verdict "
              "| train min |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for k, v in models.items():
            if split not in v:
                continue
            r, t = v[split], v["training"]
            mins = "" if t["minutes"] is None else f"{t['minutes']:.1f}"
            on = "(baseline)" if k == BASELINE else ("yes" if k in front else "no")
            print(f"| {k} | {r['l1'] * 1e3:.3f} | {r['dame'] * 1e2:.3f} | {r.get('fmpd', float('nan')) * 1e2:.3f} | "
                  f"{on} | {t['epochs']} | {t['ended']} | {t['verdict']} | {mins} |")
        for k, c in read.items():
            mean = {None: "no mean shape in the run", True: "beats the mean shape on L1 and DAME",
                    False: "does not beat the mean shape on both"}[c["beats_mean"]]
            print(f"\nC4, {k}, {split}: {'on' if c['front'] else 'off'} the front; DAME rank {c['dame_rank']} and "
                  f"L1 rank {c['l1_rank']} of {c['n']} learned models; {mean}: {c['verdict']}.")
    if a.k is not None:
        rows = k_rows(a.k)
        for split in a.splits.split(","):
            pts = [(r[split]["l1"], r[split]["dame"]) for _, r in rows]
            front = {rows[i][0] for i in pareto_front(pts)}
            print(f"\nk study ({a.k.name}), {split}\n")
            print("| k | L1 ×1e-3 | DAME ×1e-2 | FMPD ×1e-2 | on the front | verdict | train min |")
            print("| --- | --- | --- | --- | --- | --- | --- |")
            for k, r in rows:
                t = r["training"]
                mins = "" if t["minutes"] is None else f"{t['minutes']:.1f}"
                print(f"| {k} | {r[split]['l1'] * 1e3:.3f} | {r[split]['dame'] * 1e2:.3f} | "
                      f"{r[split].get('fmpd', float('nan')) * 1e2:.3f} | {'yes' if k in front else 'no'} | "
                      f"{t['verdict']} | {mins} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
