"""Claims C1 and C2 (thesis 3.5.1, 3.5.2) from a finished chapter 3 grid run (issue 13).

    python benchmarks/claims_ch3.py RUN [--split test]

RUN is a run of ``recipes/thesis/ch3/plateau.yaml`` (members ``<conv>-<representation>``, each with
``metrics.json``; unfinished members are listed as missing). Prints, in markdown:

* one row per conv: L1 and DAME (and L2, FMPD) of each representation on the split, mean over
  meshes in the evaluation space, with each member's epochs, what ended its training, the
  plateau rule's verdict (the report's Training section) and its training minutes (the sum of its
  epochs' seconds, resumed runs included);
* C1 per conv: whether a Euclidean-based representation (Euclidean or Euclidean Std.) has the
  lower L1 and L2 than DR Norm., and DR Norm. the lower DAME and FMPD than both; C1 holds "for
  most of the five convs" when it holds for at least three;
* C2 per conv: whether Euclidean Std. has a lower L1 and a lower DAME than Euclidean.

No threshold is tuned: a comparison is the sign of a difference of means.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import training  # noqa: E402

REPS = ("euclidean", "euclidean-std", "dr-norm")
CONVS = ("spiral", "spiralpp", "feast", "lsa", "vcconv")


def load(run: Path, split: str) -> dict:
    """{(conv, rep): {metric: mean, "epochs": ..., "ended": ..., "verdict": ...}} of finished members."""
    out = {}
    for conv in CONVS:
        for rep in REPS:
            f = run / f"{conv}-{rep}" / "metrics.json"
            if not f.exists():
                continue
            m = json.loads(f.read_text())
            (label, res), = m["models"].items()
            row = {k: v["mean"] for k, v in res[split].items()}
            t = training(m, label, run / f"{conv}-{rep}")
            row.update(epochs=t["epochs"], ended=t["ended"], verdict=t["verdict"], fit_min=t["minutes"])
            out[conv, rep] = row
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--split", default="test")
    a = ap.parse_args(argv)
    rows = load(a.run, a.split)
    print(f"{a.split}, evaluation space, mean over meshes ({a.run.name})\n")
    print("| conv | representation | L1 ×1e-3 | L2 ×1e-5 | DAME ×1e-2 | FMPD ×1e-2 | epochs | ended by | verdict | fit min |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for conv in CONVS:
        for rep in REPS:
            r = rows.get((conv, rep))
            if r is None:
                print(f"| {conv} | {rep} | missing | | | | | | | |")
                continue
            print(f"| {conv} | {rep} | {r['l1'] * 1e3:.3f} | {r['l2'] * 1e5:.3f} | {r['dame'] * 1e2:.3f} | "
                  f"{r['fmpd'] * 1e2:.3f} | {r['epochs']} | {r['ended']} | {r['verdict']} | "
                  f"{'' if r['fit_min'] is None else format(r['fit_min'], '.1f')} |")
    print("\n| conv | C1: Euclidean-based lower L1 | lower L2 | C1: DR Norm. lower DAME | lower FMPD | "
          "C2: Std. lower L1 | C2: Std. lower DAME |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    c1 = c2 = n = 0  # n: convs with all three members
    for conv in CONVS:
        r = {rep: rows.get((conv, rep)) for rep in REPS}
        if any(v is None for v in r.values()):
            print(f"| {conv} | incomplete | | | | | |")
            continue
        e, s, d = r["euclidean"], r["euclidean-std"], r["dr-norm"]
        yes = lambda b: "yes" if b else "no"  # noqa: E731
        l1 = min(e["l1"], s["l1"]) < d["l1"]
        l2 = min(e["l2"], s["l2"]) < d["l2"]
        dame = d["dame"] < min(e["dame"], s["dame"])
        fmpd = d["fmpd"] < min(e["fmpd"], s["fmpd"])
        std_l1, std_dame = s["l1"] < e["l1"], s["dame"] < e["dame"]
        print(f"| {conv} | {yes(l1)} | {yes(l2)} | {yes(dame)} | {yes(fmpd)} | {yes(std_l1)} | {yes(std_dame)} |")
        n += 1
        c1 += l1 and dame
        c2 += std_l1 and std_dame
    print(f"\nC1 (Euclidean-based lower L1 and DR Norm. lower DAME) holds for {c1} of {n} complete convs; "
          f"C2 (Std. lowers both L1 and DAME) for {c2} of {n}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
