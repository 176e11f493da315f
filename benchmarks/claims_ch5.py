"""Claims C5 and C6 (thesis 5.2.3 table 5.1; 5.3.5 table 5.2) from a finished chapter 5 run (issue 13).

    python benchmarks/claims_ch5.py RUN [--split test]

RUN is a run of ``recipes/thesis/ch5/plateau.yaml`` (a blendshapes run). Its models are found by
their labels: ``<x>-two-step`` is a two-step PB whose end-to-end partner is the label ending in
``:<x>`` or equal to ``<x>`` (PBS's parts reported alone are ``pbs:pb-euclidean-std`` and
``pbs:pb-dr-norm``); the cut-selecting models are those with a k sweep (metrics.json ``pbs``);
Deformation Transfer is every label starting with ``dt``. Prints, in markdown:

* C5 per pair and expression: DAME and FMPD (and L1) of end-to-end against two-step, and whether
  end-to-end is lower on both perceptual metrics. C5 "holds" for a pair when it is on most
  expressions;
* C6 per PBS model and expression: L1 and DAME of PBS against each DT source, DT's excess over
  PBS in % (the thesis: DT +61.1, +60.2 and +32.5 % in L1 on its three expressions), and
  whether PBS is lower on both. C6 "holds" when PBS is lower on both for every source on most
  expressions;
* the training of every network: epochs, what ended it, the plateau rule's verdict, minutes
  (the sum of the epochs' own seconds, a resumed run's earlier epochs included).

No threshold is tuned: a comparison is the sign of a difference of means.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def pairs(labels) -> list[tuple[str, str]]:
    """(end-to-end, two-step) label pairs: ``<x>-two-step`` with ``<x>`` or ``...:<x>``."""
    out = []
    for b in labels:
        if not b.endswith("-two-step"):
            continue
        x = b[: -len("-two-step")]
        a = next((a for a in labels if a == x or a.endswith(":" + x)), None)
        if a is not None:
            out.append((a, b))
    return out


def _most(n_yes: int, n: int) -> str:
    return "holds" if 2 * n_yes > n else ("does not hold" if n_yes == 0 else "partly")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--split", default="test", help="(the blendshapes task reports the test split)")
    a = ap.parse_args(argv)
    m = json.loads((a.run / "metrics.json").read_text())
    per = m["blendshapes"]  # {expression: {label: {metric: {mean: ...}}}}
    exprs = list(per)
    labels = list(dict.fromkeys(lb for e in exprs for lb in per[e]))
    mean = lambda e, lb, k: per[e].get(lb, {}).get(k, {}).get("mean")  # noqa: E731
    yes = lambda b: "yes" if b else "no"  # noqa: E731

    print(f"C5: end-to-end against two-step PB ({a.run.name}, {a.split}, mean over subjects, evaluation space)\n")
    print("| end-to-end | two-step | expression | L1 ×1e-3 e2e / 2-step | DAME ×1e-2 e2e / 2-step | "
          "FMPD ×1e-2 e2e / 2-step | e2e lower DAME and FMPD |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    verdicts = []
    for e2e, two in pairs(labels):
        n_yes = 0
        for e in exprs:
            v = {k: (mean(e, e2e, k), mean(e, two, k)) for k in ("l1", "dame", "fmpd")}
            ok = v["dame"][0] < v["dame"][1] and v["fmpd"][0] < v["fmpd"][1]
            n_yes += ok
            print(f"| {e2e} | {two} | {e} | {v['l1'][0] * 1e3:.3f} / {v['l1'][1] * 1e3:.3f} | "
                  f"{v['dame'][0] * 1e2:.3f} / {v['dame'][1] * 1e2:.3f} | "
                  f"{v['fmpd'][0] * 1e2:.3f} / {v['fmpd'][1] * 1e2:.3f} | {yes(ok)} |")
        verdicts.append(f"C5, {e2e} against {two}: end-to-end lower on both perceptual metrics for {n_yes} of "
                        f"{len(exprs)} expressions: {_most(n_yes, len(exprs))}.")
    print("\n" + "\n".join(verdicts))

    pbs = [lb for lb in m.get("pbs", {}) if lb in labels]
    dts = [lb for lb in labels if lb.startswith("dt")]
    print(f"\nC6: PBS against Deformation Transfer ({a.split})\n")
    print("| PBS | DT | expression | k | L1 ×1e-3 PBS / DT | DT's L1 excess | DAME ×1e-2 PBS / DT | DT's DAME excess "
          "| PBS lower on both |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    verdicts = []
    for p in pbs:
        n_yes = 0
        for e in exprs:
            k = m["pbs"][p].get("k", {}).get(e, "")
            all_ok = True
            for d in dts:
                l1 = (mean(e, p, "l1"), mean(e, d, "l1"))
                dame = (mean(e, p, "dame"), mean(e, d, "dame"))
                ok = l1[0] < l1[1] and dame[0] < dame[1]
                all_ok &= ok
                print(f"| {p} | {d} | {e} | {k} | {l1[0] * 1e3:.3f} / {l1[1] * 1e3:.3f} | {(l1[1] / l1[0] - 1) * 100:+.1f} % "
                      f"| {dame[0] * 1e2:.3f} / {dame[1] * 1e2:.3f} | {(dame[1] / dame[0] - 1) * 100:+.1f} % | {yes(ok)} |")
            n_yes += all_ok
        verdicts.append(f"C6, {p}: lower L1 and DAME than every DT source for {n_yes} of {len(exprs)} expressions: "
                        f"{_most(n_yes, len(exprs))}.")
    print("\n" + "\n".join(verdicts))

    nets = m.get("training", {}).get("networks", {})
    if nets:
        print("\n| network | epochs | ended by | verdict | train min |\n| --- | --- | --- | --- | --- |")
        for name, t in nets.items():
            mins = "" if t.get("train_s") is None else f"{t['train_s'] / 60:.1f}"
            print(f"| {name} | {t['epochs_run']}/{t['max_epochs']} | {t['stopped_by']} | {t['plateau']} | {mins} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
